"""``python -m eabc.cli``: the ``eabc`` command."""

from eabc.cli import main

main()
