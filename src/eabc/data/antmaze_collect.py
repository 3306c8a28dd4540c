"""AntMaze data by D4RL's recipe: the direction-following Ant policy steered through a maze by the
waypoint planner, several environments at once.

Two recipes (:data:`RECIPES`), recorded in every file: ``faithful-v1``, the default, follows
D4RL's generation script and its dataset flags point by point (docs/datasets.md has the table);
``planner-v0`` is the first recipe, kept so that its datasets and results stay reproducible
(``antmaze-umaze@planner-v0``). What follows describes ``planner-v0``; :class:`Recipe` says where
``faithful-v1`` differs.

D4RL's ``scripts/generation/generate_ant_maze_datasets.py`` in our terms: every step, the
breadth-first-search planner (:class:`eabc.data.mazes.WaypointPlanner`) gives the next cell's centre
plus ``U(0, 1)`` noise per axis (the goal itself once in the goal's cell; the ant first reaches the
middle of each cell it enters before it turns toward the next), the low-level policy sees the
ant's state and the unit vector toward that waypoint (:func:`eabc.data.antmaze.lowlevel_observation`),
and Gaussian noise of standard deviation 0.2 is added to its action, clipped to [-1, 1]. The ant does
not stop at the goal (it stays around it until the time limit), so every episode has the maze's
full length, 700 steps in umaze and 1,000 otherwise, and ends in a timeout.

Starts and goals per dataset family (:data:`FAMILIES`); the rewards are relabelled afterwards
against the evaluation goal (:func:`eabc.data.mazes.relabel`).

The low-level policy is the zoo's ``antmaze/direction.npz`` (:func:`load_policy`), its card
``antmaze/card.json``; ``eabc zoo build RUN_DIR antmaze`` makes both from an ``eabc sac`` run on
``eabc/AntDirection-v0``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import numpy as np

from eabc import numpy_networks
from eabc.data import antmaze, mazes, zoo
from eabc.data.dataset import Dataset, DatasetError
from eabc.data.mazes import Cell, Maze
from eabc.progress import bar as progress_bar

ACTION_NOISE = 0.2
"""Standard deviation of the Gaussian noise on every action (D4RL's ``--noisy``)."""
NUM_ENVS = 10
"""Environments stepped together, the policy batched over them. Part of the recipe: the batched
product's float64 sums may round differently for another batch size."""
ZOO_ENTRY = "antmaze"
POLICY_FILE = "direction.npz"

FAMILIES = {
    "fixed": "D4RL's antmaze-umaze: every episode from the start cell (D4RL's reset noise) to the "
    "evaluation goal cell",
    "diverse": "random goals from random starts: start and goal cells drawn uniformly from the "
    "free cells (different ones), the start with D4RL's U(0, 1) multi-start noise",
    "play": "hand-picked goals from hand-picked starts: goals from the goal cells of the map D4RL's "
    "generation script rolled out in (its G cells), starts from those and the start cell",
}
"""How an episode chooses its start and goal cell; the goal point is the cell's centre plus D4RL's
goal noise, ``U(0, 1) + U(0, 0.5)`` per axis (:class:`eabc.data.antmaze.AntMazeEnv`)."""

D4RL_FAMILIES = {
    "fixed": "D4RL's antmaze-umaze, no --multi_start: from the start cell (reset noise only) to "
    "the map's goal cell",
    "play": "--multi_start: from a uniformly random free cell that is not a goal cell to a "
    "uniformly random goal cell of the map D4RL's script rolled out in",
    "diverse": "--multi_start --multigoal: start and goal cells each uniform over the free cells",
}
"""The families as D4RL's files were made (:func:`d4rl_episode_cells`; recipe ``faithful-v1``)."""


@dataclasses.dataclass(frozen=True)
class Recipe:
    """How the controller collects an AntMaze dataset's episodes."""

    name: str
    sample_actions: bool
    """Actions drawn from the policy's tanh-Gaussian before the noise (D4RL's ``get_action`` of
    rlkit's ``exploration/policy``), else its mean action."""
    d4rl_planner: bool
    """D4RL's memoryless waypoint rule (:func:`eabc.data.mazes.d4rl_waypoint`), else
    :class:`eabc.data.mazes.WaypointPlanner`, which centres in every cell before it turns."""
    d4rl_cells: bool
    """Starts and goals by D4RL's dataset flags (:func:`d4rl_episode_cells`), else
    :data:`FAMILIES` (:func:`episode_cells`)."""
    episode_steps: int | None
    """Transitions per episode; None: the maze's evaluation limit (700 in umaze, else 1,000)."""

    def steps(self, maze: Maze) -> int:
        return self.episode_steps or maze.max_episode_steps


D4RL_EPISODE_STEPS = 1001
"""D4RL's script flags a timeout once its step counter, from 0, reaches ``--max_episode_steps``
(default 1,000) and counts after: 1,001 transitions per episode, in every maze."""
RECIPES = {
    "faithful-v1": Recipe("faithful-v1", True, True, True, D4RL_EPISODE_STEPS),
    "planner-v0": Recipe("planner-v0", False, False, False, None),
}
"""The AntMaze recipes by name; a dataset name ``antmaze-KIND@RECIPE`` asks for one by name."""
DEFAULT_RECIPE = "faithful-v1"
LEGACY_RECIPE = "planner-v0"
"""The recipe of files that record none (made before recipes had names)."""


def recipe(name: str | None = None) -> Recipe:
    """The recipe called ``name`` (None: the default); an unknown name is refused with the known."""
    name = name or DEFAULT_RECIPE
    if name not in RECIPES:
        raise DatasetError(f"unknown AntMaze recipe {name!r}; the recipes are {', '.join(RECIPES)}")
    return RECIPES[name]


def split_name(name: str) -> tuple[str, str]:
    """``(dataset name without the recipe, recipe name)``: ``antmaze-umaze@planner-v0`` ->
    ``("antmaze-umaze", "planner-v0")``, ``antmaze-umaze`` -> ``("antmaze-umaze", "faithful-v1")``."""
    base, _, which = name.partition("@")
    return base, recipe(which or None).name


def dataset_family(kind: str) -> tuple[str, str]:
    """``(maze, family)`` of an AntMaze dataset kind: ``medium-play`` -> ``("medium", "play")``."""
    maze, _, family = kind.partition("-")
    return maze, family or "fixed"


def episode_cells(maze: Maze, family: str, rng: np.random.Generator) -> tuple[Cell | None, Cell]:
    """``(start cell, goal cell)`` of one episode; a start of None is the maze's own start."""
    if family == "fixed":
        return None, maze.goal_cell
    if family == "diverse":
        cells = maze.free_cells
        start, goal = rng.choice(len(cells), size=2, replace=False)
        return cells[start], cells[goal]
    if family == "play":
        goals = maze.generation_goals
        goal = goals[rng.integers(len(goals))]
        starts = [cell for cell in (maze.start_cell, *goals) if cell != goal]
        return starts[rng.integers(len(starts))], goal
    raise ValueError(f"unknown AntMaze family {family!r}; known: {', '.join(FAMILIES)}")


def d4rl_episode_cells(
    maze: Maze, family: str, rng: np.random.Generator
) -> tuple[Cell | None, Cell]:
    """``(start cell, goal cell)`` of one episode as D4RL's files were made (their names carry the
    flags): umaze without ``--multi_start``, from the start cell (reset noise only) to the map's
    goal cell; play with ``--multi_start``, from a uniformly random free cell that is not a goal
    cell (``_get_reset_location`` counts goal cells as walls) to a uniformly random goal cell of
    the generation map (``goal_sampler``); diverse with ``--multi_start --multigoal``, start and
    goal each uniform over the free cells (``goal_sampler`` of a map with no goal cells: the
    published script does not read ``--multigoal``, D4RL's paper says random goals)."""
    if family == "fixed":
        return None, maze.goal_cell
    if family == "play":
        goals = maze.generation_goals
        starts = [cell for cell in maze.free_cells if cell not in goals]
        return starts[rng.integers(len(starts))], goals[rng.integers(len(goals))]
    if family == "diverse":
        cells = maze.free_cells
        return cells[rng.integers(len(cells))], cells[rng.integers(len(cells))]
    raise ValueError(f"unknown AntMaze family {family!r}; known: {', '.join(FAMILIES)}")


def policy_path(root: str | os.PathLike | None = None) -> Path:
    return zoo.zoo_dir(root) / ZOO_ENTRY / POLICY_FILE


def load_policy(root: str | os.PathLike | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """The zoo's low-level direction-following actor and its card."""
    path = policy_path(root)
    if not path.exists():
        raise DatasetError(
            f"the zoo has no AntMaze low-level policy ({path} is missing); train one with `eabc "
            f"sac --env {antmaze.DIRECTION_ENV_ID}` and add it with `eabc zoo build RUN_DIR antmaze`"
        )
    card_path = path.parent / zoo.CARD
    card = json.loads(card_path.read_text()) if card_path.exists() else {}
    return zoo.load_actor(path), card


def policy_fingerprint(root: str | os.PathLike | None = None) -> str:
    """A digest of the low-level policy's weights, kept in every dataset made with it."""
    return hashlib.sha256(policy_path(root).read_bytes()).hexdigest()[:16]


@dataclasses.dataclass
class Collected:
    """Transitions of whole episodes, in episode order, and how each episode went."""

    observations: np.ndarray
    actions: np.ndarray
    next_observations: np.ndarray
    goals: np.ndarray
    """Each episode's commanded goal, ``[episodes, 2]``."""
    success: np.ndarray
    """Whether the ant came within 0.5 of its episode's goal."""
    flipped: np.ndarray
    """Whether the torso turned upside down (its z axis pointing below the horizon)."""

    def summary(self) -> dict:
        return {
            "episodes": int(len(self.success)),
            "success_rate": float(self.success.mean()),
            "flip_rate": float(self.flipped.mean()),
        }


def upside_down(obs: np.ndarray) -> np.ndarray:
    """Whether the torso's z axis points below the horizon, from D4RL's observation's quaternion."""
    quat = obs[..., 3:7]
    return 1.0 - 2.0 * (quat[..., 1] ** 2 + quat[..., 2] ** 2) < 0.0


def collect(
    maze_name: str,
    family: str,
    episodes: int,
    seed: int,
    actor: dict[str, np.ndarray],
    max_episode_steps: int | None = None,
    num_envs: int = NUM_ENVS,
    action_noise: float = ACTION_NOISE,
    desc: str = "antmaze",
    first: int = 0,
    stop: int | None = None,
    progress: bool = True,
    recipe_name: str = DEFAULT_RECIPE,
) -> Collected:
    """Roll out ``episodes`` controller episodes in ``maze_name`` (:data:`FAMILIES`), or of them
    only episodes ``first`` (a multiple of ``num_envs``) to ``stop``: batches are independent.

    Episode ``i`` draws everything (cells, reset, waypoint and action noise) from its own generator
    seeded with ``(seed, i)``: the data are the same for a seed, whatever the number of episodes.
    ``recipe_name`` names the :data:`RECIPES` entry.
    """
    maze = mazes.get(maze_name)
    how = recipe(recipe_name)
    steps = max_episode_steps or how.steps(maze)
    act = _actions(actor, how.sample_actions)
    cells_of = d4rl_episode_cells if how.d4rl_cells else episode_cells
    envs = [antmaze.AntMazeEnv(maze.name, terminate_on_success=False) for _ in range(num_envs)]
    stop = episodes if stop is None else stop
    if first % num_envs or not 0 <= first < stop <= episodes:
        raise ValueError(f"episodes {first} to {stop} of {episodes} are not whole batches")
    rows = (stop - first) * steps
    obs_out = np.empty((rows, antmaze.OBS_DIM), np.float32)
    next_out = np.empty((rows, antmaze.OBS_DIM), np.float32)
    act_out = np.empty((rows, envs[0].action_space.shape[0]), np.float32)
    goals = np.empty((stop - first, 2))
    success, flipped = np.zeros(stop - first, bool), np.zeros(stop - first, bool)
    bar = progress_bar(rows, desc, enabled=progress, mininterval=1.0, leave=False)
    for batch in range(first, stop, num_envs):
        # Always a full batch (the policy's batch size stays the same); extra episodes are dropped.
        ids = range(batch, batch + num_envs)
        rngs = [np.random.default_rng([seed, i]) for i in ids]
        obs = []
        for env, rng in zip(envs, rngs):
            start, goal = cells_of(maze, family, rng)
            options = {"goal_cell": goal} | ({"start_cell": start} if start is not None else {})
            obs.append(env.reset(seed=int(rng.integers(2**63)), options=options)[0])
        obs = np.array(obs)
        batch_goals = np.array([env.goal for env in envs])
        planners = [_planner(maze, g, how) for g in batch_goals]
        reached, flips = np.zeros(num_envs, bool), np.zeros(num_envs, bool)
        live = [k for k, i in enumerate(ids) if i < stop]
        for t in range(steps):
            targets = [plan(o[:2], r) for plan, o, r in zip(planners, obs, rngs)]
            low = np.stack([antmaze.lowlevel_observation(o, w) for o, w in zip(obs, targets)])
            actions = act(low, rngs)
            noise = np.stack([r.standard_normal(actions.shape[1]) for r in rngs])
            actions = np.clip(actions + action_noise * noise, -1.0, 1.0).astype(np.float32)
            next_obs = np.array([env.step(a)[0] for env, a in zip(envs, actions)])
            reached |= mazes.is_success(next_obs[:, :2], batch_goals)
            flips |= upside_down(next_obs)
            for k in live:
                row = (batch - first + k) * steps + t
                obs_out[row], act_out[row], next_out[row] = obs[k], actions[k], next_obs[k]
            obs = next_obs
            bar.update(len(live))
        for k in live:
            goals[batch - first + k], success[batch - first + k] = batch_goals[k], reached[k]
            flipped[batch - first + k] = flips[k]
    bar.close()
    return Collected(obs_out, act_out, next_out, goals, success, flipped)


def _actions(actor: dict[str, np.ndarray], sample: bool):
    """``act(obs, rngs)``: a batch of actions in float64, row ``k`` sampled with ``rngs[k]`` from
    the tanh-Gaussian (``sample``) or the mean action ``tanh(mean)``."""
    if not sample:
        mean_action = numpy_networks.numpy_actor(actor, 1.0, gaussian=True)
        return lambda obs, rngs: mean_action(obs).astype(np.float64)
    apply = numpy_networks.numpy_mlp(actor)

    def act(obs: np.ndarray, rngs) -> np.ndarray:
        mean, log_std = np.split(np.asarray(apply(obs), np.float64), 2, axis=-1)
        std = np.exp(np.clip(log_std, numpy_networks.LOG_STD_MIN, numpy_networks.LOG_STD_MAX))
        eps = np.stack([r.standard_normal(mean.shape[1]) for r in rngs])
        return np.tanh(mean + std * eps)

    return act


def _planner(maze: Maze, goal, how: Recipe):
    """``waypoint(xy, rng)`` toward ``goal`` for one episode, by the recipe's rule."""
    if how.d4rl_planner:
        return lambda xy, rng: mazes.d4rl_waypoint(maze, xy, goal, rng)
    return mazes.WaypointPlanner(maze, goal)


OPEN_PLANE_DISTANCE = (5.0, 10.0)
"""How far the open-plane goals are from the start, metres (drawn uniformly, in a uniform direction)."""
OPEN_PLANE_STEPS = 700
"""The open-plane time limit: the shortest maze's (umaze, 70 s)."""


def open_plane(
    actor: dict[str, np.ndarray],
    episodes: int,
    seed: int,
    action_noise: float = ACTION_NOISE,
    steps: int = OPEN_PLANE_STEPS,
    distance: tuple[float, float] = OPEN_PLANE_DISTANCE,
) -> dict:
    """The low-level policy alone on the open plane: how often, fed the unit vector toward a goal
    5-10 m away (as the controller feeds it the waypoint's), it comes within 0.5 m of the goal
    within the time limit, how often the ant flips on the way (until the goal or the limit), and
    the median steps to the goal. Episode ``i`` draws from a generator seeded with ``(seed, i)``."""
    act = numpy_networks.numpy_actor(actor, 1.0, gaussian=True)
    env = antmaze.AntDirectionEnv()
    success, flipped, taken = np.zeros(episodes, bool), np.zeros(episodes, bool), []
    for i in range(episodes):
        rng = np.random.default_rng([seed, i])
        obs, _ = env.reset(seed=int(rng.integers(2**63)))
        state = np.concatenate([env.xy, obs[:-2]])  # the direction task's view, x and y put back
        angle = rng.uniform(0.0, 2.0 * np.pi)
        goal = env.xy + rng.uniform(*distance) * np.array([np.cos(angle), np.sin(angle)])
        for t in range(steps):
            action = act(antmaze.lowlevel_observation(state, goal)[None]).astype(np.float64)[0]
            action += action_noise * rng.standard_normal(action.shape)
            state = env.advance(np.clip(action, -1.0, 1.0))
            flipped[i] |= bool(upside_down(state))
            if mazes.is_success(state[:2], goal):
                success[i] = True
                taken.append(t + 1)
                break
    return {
        "episodes": episodes,
        "goal_distance_m": list(distance),
        "time_limit_steps": steps,
        "success_rate": float(success.mean()),
        "flip_rate": float(flipped.mean()),
        "median_steps_to_goal": float(np.median(taken)) if taken else None,
    }


def make_dataset(
    name: str,
    kind: str,
    size: int,
    seed: int,
    actor: dict[str, np.ndarray],
    num_envs: int = NUM_ENVS,
    recipe_name: str = DEFAULT_RECIPE,
) -> tuple[Dataset, dict]:
    """``size`` transitions of the AntMaze dataset ``antmaze-KIND`` by the recipe
    ``recipe_name``, relabelled against the evaluation goal; the transitions and a summary of the
    controller's episodes."""
    maze_name, family = dataset_family(kind)
    episodes = episodes_for(kind, size, recipe_name)
    data = collect(
        maze_name, family, episodes, seed, actor, num_envs=num_envs, desc=name,
        recipe_name=recipe_name,
    )  # fmt: skip
    return relabelled(name, kind, size, data, num_envs, recipe_name)


def episodes_for(kind: str, size: int, recipe_name: str = DEFAULT_RECIPE) -> int:
    """Whole episodes that ``size`` transitions of ``antmaze-KIND`` are cut from."""
    return -(-size // recipe(recipe_name).steps(mazes.get(dataset_family(kind)[0])))


def relabelled(
    name: str, kind: str, size: int, data: Collected, num_envs: int,
    recipe_name: str = DEFAULT_RECIPE,
) -> tuple[Dataset, dict]:  # fmt: skip
    """:func:`make_dataset`'s result from the collected episodes ``data``."""
    maze_name, family = dataset_family(kind)
    maze = mazes.get(maze_name)
    how = recipe(recipe_name)
    steps = how.steps(maze)
    goal = relabel_goal(maze)
    rewards, terminals = mazes.relabel(data.next_observations[:size, :2], goal)
    timeouts = np.zeros(size, bool)
    timeouts[steps - 1 :: steps] = True
    timeouts[-1] = True
    dataset = Dataset(
        observations=data.observations[:size],
        actions=data.actions[:size],
        rewards=rewards,
        next_observations=data.next_observations[:size],
        terminals=terminals,
        timeouts=timeouts,
        name=name,
    )
    summary = {
        **data.summary(),
        "recipe": dataclasses.asdict(how),
        "family": family,
        "family_rule": (D4RL_FAMILIES if how.d4rl_cells else FAMILIES)[family],
        "relabel_goal": goal.tolist(),
        "action_noise": ACTION_NOISE,
        "num_envs": num_envs,
    }
    return dataset, summary


def relabel_goal(maze: Maze) -> np.ndarray:
    """The goal the rewards are relabelled against: the evaluation goal cell's centre plus 0.75 per
    axis, the middle of where evaluation draws its goal (``U(0, 1) + U(0, 0.5)``). D4RL relabelled
    against one such draw."""
    return maze.goal_xy + 0.75


def position_jumps(dataset: Dataset, max_step: float = 1.0) -> dict:
    """Transitions whose episode continues (no timeout) but whose position does not: the next
    row's observation is not this row's next observation, or the torso moved more than
    ``max_step`` metres in one step (the ant walks about 0.2 m per 0.1 s step)."""
    xy, next_xy = dataset.observations[:, :2], dataset.next_observations[:, :2]
    moved = np.linalg.norm(next_xy - xy, axis=1) > max_step
    continues = ~dataset.timeouts[:-1]
    broken = continues & np.any(dataset.observations[1:] != dataset.next_observations[:-1], axis=1)
    rows = np.flatnonzero(np.append(broken, False) | moved)
    return {"count": int(len(rows)), "first_rows": rows[:5].tolist()}


def maze_of_env(env_id: str | None) -> Maze | None:
    """The maze whose evaluation environment is ``env_id`` (None: not an AntMaze environment)."""
    return next((mazes.MAZES[m] for m, i in antmaze.ENV_IDS.items() if i == env_id), None)


def checks(dataset: Dataset) -> dict:
    """What ``eabc data info`` reports of an AntMaze dataset: the controller's success rate as
    recorded when it was made, the reward-1 transitions, and the position jumps."""
    controller = dataset.metadata.get("controller", {})
    return {
        "controller_success_rate": controller.get("success_rate"),
        "controller_flip_rate": controller.get("flip_rate"),
        "controller_episodes": controller.get("episodes"),
        "reward_1_transitions": int((dataset.rewards == 1).sum()),
        "position_jumps_without_timeout": position_jumps(dataset),
    }


def plot_coverage(dataset: Dataset, path: str | os.PathLike) -> Path:
    """A PNG of where the data's torso positions lie over the maze's walls (log-scaled counts),
    with the start cell and the relabelling goal's 0.5 m circle."""
    maze = maze_of_env(dataset.env_id)
    if maze is None:
        raise DatasetError(
            f"{dataset.name}: --plot draws AntMaze data over its maze, but the data's environment "
            f"is {dataset.env_id!r}, not one of {', '.join(antmaze.ENV_IDS.values())}"
        )
    from matplotlib.colors import LogNorm  # noqa: PLC0415 (only --plot draws: not on every start)
    from matplotlib.figure import Figure  # noqa: PLC0415 (only --plot draws: not on every start)
    from matplotlib.patches import Circle, Rectangle  # noqa: PLC0415 (only --plot draws)

    half = mazes.SCALING / 2
    rows, cols = maze.shape
    low, high = maze.cell_to_xy((0, 0)) - half, maze.cell_to_xy((rows - 1, cols - 1)) + half
    fig = Figure(figsize=(1 + cols * 0.7, 1 + rows * 0.7), dpi=120)
    ax = fig.subplots()
    xy = dataset.observations[:, :2]
    *_, image = ax.hist2d(
        xy[:, 0], xy[:, 1], bins=(cols * 16, rows * 16), range=list(zip(low, high)),
        norm=LogNorm(), cmap="viridis",
    )  # fmt: skip
    for cell in maze.wall_cells:
        x, y = maze.cell_to_xy(cell) - half
        ax.add_patch(Rectangle((x, y), mazes.SCALING, mazes.SCALING, color="0.35"))
    ax.plot(*maze.start_xy, "o", color="white", markeredgecolor="black", label="start")
    goal = Circle(relabel_goal(maze), mazes.GOAL_TOLERANCE, fill=False, color="red", lw=2)
    ax.add_patch(goal)
    ax.plot([], [], "o", mfc="none", color="red", label="goal (reward 1)")
    ax.set(xlim=(low[0], high[0]), ylim=(low[1], high[1]), aspect="equal", xlabel="x", ylabel="y")
    ax.set_title(f"{dataset.name}: {dataset.size:,} positions", fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    fig.colorbar(image, ax=ax, label="transitions per bin")
    path = Path(path)
    fig.savefig(path, bbox_inches="tight")
    return path
