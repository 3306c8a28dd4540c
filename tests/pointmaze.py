"""A point mass in D4RL's U-maze: AntMaze's task, conventions and data pipeline without the ant,
for a learning test that runs in seconds.

The maze, start and goal cells, goal noise, tolerance, planner and relabelling are AntMaze's own
(:mod:`eabc.data.mazes`, :func:`eabc.data.antmaze_collect.episode_cells` and
:func:`~eabc.data.antmaze_collect.relabel_goal`); only the body differs: the observation is the
position x, y and an action in [-1, 1]^2 moves the point by up to :data:`SPEED` metres per step.
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np

from eabc.data import antmaze_collect, hdf5_writer, mazes, tasks
from eabc.data.dataset import Dataset

ENV_ID = "eabc-test/PointUMaze-v0"
MAZE = mazes.MAZES["umaze"]
SPEED = 2.0
"""Metres per step at full action: the way from the start to the goal, about 24 m, takes 12 steps
(fewer steps for the value to propagate over: the test learns in a few thousand updates)."""
MAX_EPISODE_STEPS = 30
"""The time limit of evaluation and of the data's episodes (AntMaze's are the same for both too)."""
ACTION_NOISE = 0.3
"""Gaussian noise on the controller's actions (D4RL's ant: 0.2 on its joint torques)."""


class PointMazeEnv(gym.Env):
    """AntMaze's evaluation in :data:`MAZE` with a point for a body: from the start cell (reset
    noise ``U(-0.1, 0.1)``) to the goal cell's centre plus D4RL's goal noise ``U(0, 1) + U(0,
    0.5)`` per axis, reward 1 and the episode's end within 0.5 of the goal. A move that would
    enter a wall cell is dropped per axis. ``reset(options=...)`` and ``terminate_on_success``
    as :class:`eabc.data.antmaze.AntMazeEnv`'s."""

    metadata = {"render_modes": []}

    def __init__(self, terminate_on_success: bool = True):
        self.terminate_on_success = terminate_on_success
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float64)
        self.xy, self.goal = MAZE.start_xy, MAZE.goal_xy

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options, rng = options or {}, self.np_random
        goal_cell = tuple(options.get("goal_cell") or MAZE.goal_cell)
        self.goal = MAZE.cell_to_xy(goal_cell) + rng.uniform(0, 1, 2) + rng.uniform(0, 0.5, 2)
        start_cell = options.get("start_cell")
        if start_cell is None:
            self.xy = MAZE.start_xy + rng.uniform(-0.1, 0.1, 2)
        else:
            self.xy = MAZE.cell_to_xy(tuple(start_cell)) + rng.uniform(0, 1, 2)
        return self.xy.copy(), {"goal": self.goal.copy()}

    def step(self, action):
        move = SPEED * np.clip(np.asarray(action, np.float64), -1.0, 1.0)
        for axis in (0, 1):
            moved = self.xy.copy()
            moved[axis] += move[axis]
            if MAZE.is_free(MAZE.xy_to_cell(moved)):
                self.xy = moved
        success = bool(mazes.is_success(self.xy, self.goal))
        info = {"goal": self.goal.copy(), "success": success}
        return self.xy.copy(), float(success), success and self.terminate_on_success, False, info


def register() -> None:
    if ENV_ID not in gym.registry:
        gym.register(ENV_ID, entry_point=PointMazeEnv, max_episode_steps=MAX_EPISODE_STEPS)


def controller(planner: mazes.WaypointPlanner, xy, rng: np.random.Generator) -> np.ndarray:
    """Toward the planner's waypoint at full speed (slower within a step of it), plus noise."""
    offset = planner(xy, rng) - xy
    action = offset / max(float(np.linalg.norm(offset)), SPEED)
    return np.clip(action + ACTION_NOISE * rng.standard_normal(2), -1.0, 1.0).astype(np.float32)


def make_dataset(path: str | Path, episodes: int, seed: int, family: str = "diverse") -> Path:
    """``episodes`` whole episodes of the noisy planner-driven point (starts and goals by AntMaze's
    ``family``; the point stays around its goal until the time limit, as the ant does),
    relabelled against the evaluation goal and written as the AntMaze datasets are: D4RL's HDF5
    layout with the evaluation env, reference scores 0 and 1 and the reward offset -1."""
    env = PointMazeEnv(terminate_on_success=False)
    rows = {k: [] for k in ("observations", "actions", "next_observations")}
    timeouts = []
    for episode in range(episodes):
        rng = np.random.default_rng([seed, episode])
        start, goal = antmaze_collect.episode_cells(MAZE, family, rng)
        options = {"goal_cell": goal} | ({"start_cell": start} if start is not None else {})
        obs, _ = env.reset(seed=int(rng.integers(2**63)), options=options)
        planner = mazes.WaypointPlanner(MAZE, env.goal)
        for t in range(MAX_EPISODE_STEPS):
            action = controller(planner, obs, rng)
            next_obs = env.step(action)[0]
            for key, value in zip(rows, (obs, action, next_obs)):
                rows[key].append(value)
            timeouts.append(t == MAX_EPISODE_STEPS - 1)
            obs = next_obs
    arrays = {k: np.array(v, np.float32) for k, v in rows.items()}
    rewards, terminals = mazes.relabel(
        arrays["next_observations"], antmaze_collect.relabel_goal(MAZE)
    )
    env_info = tasks.env_info(("antmaze", "umaze"))
    dataset = Dataset(
        **arrays,
        rewards=rewards,
        terminals=terminals,
        timeouts=np.array(timeouts),
        name=f"pointmaze-umaze-{family}",
        env_id=ENV_ID,
        ref_min_score=env_info.ref_min_score,
        ref_max_score=env_info.ref_max_score,
        reward_offset=tasks.reward_offset(("antmaze", "umaze")),
        metadata={"family": family, "seed": seed},
    )
    return hdf5_writer.save_hdf5(dataset, path)
