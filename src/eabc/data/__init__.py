"""Datasets: loading, making and describing them. Importing this package puts the package's own
Gymnasium environments (``eabc/AntMaze-*-v0``, ``eabc/AntDirection-v0``) in Gymnasium's registry,
so that ``gym.make`` finds them wherever an environment id is given (``eabc sac --env``)."""

from eabc.data import antmaze as _antmaze

_antmaze.register()
