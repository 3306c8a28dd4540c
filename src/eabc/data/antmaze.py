"""The AntMaze environments, on D4RL's ant: the evaluation mazes and the open plane the low-level
direction-following policy trains on.

Both run D4RL's ant (``d4rl/locomotion/assets/ant.xml``: timestep 0.02 s with RK4, 5 substeps, so
0.1 s per step; motors clipped to +-30, reached by actions in [-1, 1] as D4RL's
``NormalizedBoxEnv`` scales them) in MuJoCo's own Python bindings, walls placed as D4RL places
them (:mod:`eabc.data.mazes`). The model is built at run time from the ``ant.xml`` that the
installed Gymnasium ships, edited to D4RL's values (:data:`D4RL_EDITS`). Why not
Gymnasium-Robotics' AntMaze: see docs/datasets.md.

Observations (float64):

- ``eabc/AntMaze-{UMaze,Medium,Large}-v0``, 29 values, D4RL's layout: ``[0:2]`` torso x, y (D4RL's
  world coordinates); ``[2]`` torso z; ``[3:7]`` torso orientation quaternion (w, x, y, z);
  ``[7:15]`` the 8 joint angles in body order (hip_1, ankle_1, ..., hip_4, ankle_4; the actions
  drive them in D4RL's actuator order hip_4, ankle_4, hip_1, ankle_1, ..., hip_3, ankle_3);
  ``[15:18]`` torso linear velocity; ``[18:21]`` torso angular velocity; ``[21:29]`` the 8 joint
  velocities.
  That is ``qpos[:15]`` then ``qvel[:14]``, D4RL's ``expose_all_qpos`` observation.
- ``eabc/AntDirection-v0``, 29 values: the same without x, y (``qpos[2:15]``, ``qvel[:14]``, 27
  values) followed by the unit direction to walk in (2 values, world frame).
"""

from __future__ import annotations

from pathlib import Path
from xml.etree import ElementTree

import gymnasium as gym
import numpy as np

from eabc.data import mazes, tasks
from eabc.data.mazes import Maze

D4RL_EDITS: dict[str, dict[str, str | None]] = {
    # XPath in Gymnasium's ant.xml -> the attributes D4RL's ant.xml gives it (None: remove).
    "./compiler": {"coordinate": None},  # MuJoCo >= 2.3.3 rejects it; "local" is its only mode
    "./option": {"timestep": "0.02"},  # Gymnasium: 0.01 (RK4 in both)
    "./default/geom": {"solref": ".02 1", "solimp": ".8 .8 .01"},  # Gymnasium: MuJoCo's defaults
    "./asset/texture[@name='texplane']": {"rgb1": "0.2 0.3 0.4", "rgb2": "0.1 0.2 0.3"},
    "./asset/material[@name='MatPlane']": {"reflectance": "0.0"},
    ".//body[@name='torso']/geom[@name='torso_geom']": {"rgba": "0.3 0.9 0.5 1"},
    ".//body[@name='torso']/joint[@name='root']": {"axis": "0 0 1"},
    "./actuator/motor": {"gear": None, "ctrlrange": "-30.0 30.0"},  # Gymnasium: gear 150, +-1
}
"""Where D4RL's ``d4rl/locomotion/assets/ant.xml`` (rllab's ant through efficient-hrl) differs from
Gymnasium's ``envs/mujoco/assets/ant.xml``; Gymnasium's also has a tracking camera, which D4RL's
lacks. Bodies, geoms, joints (ranges, damping 1, armature 1), density 5, friction, margins and the
torso's start height 0.75 are the same in both. With these edits the compiled model equals the one
of D4RL's file in every field (checked field by field and by bit-identical rollouts when the
embedded copy was replaced; tests/data/test_antmaze.py pins the physical values)."""
FRAME_SKIP = 5
"""Physics steps per environment step (D4RL's AntEnv)."""
TORQUE_LIMIT = 30.0
"""The motors' ctrlrange; an action of 1 is this torque (D4RL's NormalizedBoxEnv)."""
WALL_HEIGHT = 0.5
"""D4RL's ``maze_height``: walls are ``0.5 * scaling`` = 2 m high."""
HEALTHY_Z = (0.2, 1.0)
"""D4RL's AntEnv calls the ant done when its torso leaves this height range."""
OBS_DIM = 29


def gymnasium_ant_xml() -> Path:
    """Gymnasium's own ``ant.xml``, shipped in the installed package."""
    return Path(gym.__file__).parent / "envs" / "mujoco" / "assets" / "ant.xml"


def model_xml(maze: Maze | None = None) -> str:
    """D4RL's ant as MJCF: Gymnasium's ``ant.xml`` edited to D4RL's (:data:`D4RL_EDITS`), with
    ``maze``'s walls as D4RL's ``MazeEnv`` adds them (none: the open plane)."""
    root = ElementTree.parse(gymnasium_ant_xml()).getroot()
    for path, attributes in D4RL_EDITS.items():
        elements = root.findall(path)
        if not elements:
            raise RuntimeError(f"{gymnasium_ant_xml()} has no {path}: Gymnasium's ant changed")
        for element in elements:
            for key, value in attributes.items():
                if value is None:
                    element.attrib.pop(key, None)
                else:
                    element.set(key, value)
    torso = root.find(".//body[@name='torso']")
    for camera in torso.findall("camera"):
        torso.remove(camera)
    worldbody = root.find("worldbody")
    half, height = 0.5 * mazes.SCALING, WALL_HEIGHT / 2 * mazes.SCALING
    for cell in maze.wall_cells if maze is not None else []:
        x, y = maze.cell_to_xy(cell)
        ElementTree.SubElement(
            worldbody,
            "geom",
            name=f"block_{cell[0]}_{cell[1]}",
            pos=f"{x:f} {y:f} {height:f}",
            size=f"{half:f} {half:f} {height:f}",
            type="box",
            material="",
            contype="1",
            conaffinity="1",
            rgba="0.7 0.5 0.3 1.0",
        )
    return ElementTree.tostring(root, encoding="unicode")


class _Ant(gym.Env):
    """D4RL's ant in MuJoCo: actions in [-1, 1] as torques of +-30, 0.1 s per step."""

    metadata = {"render_modes": []}

    def __init__(self, maze: Maze | None):
        import mujoco  # noqa: PLC0415 (every eabc.data import registers the ants; MuJoCo loads with the first)

        self._mujoco = mujoco
        self.model = mujoco.MjModel.from_xml_string(model_xml(maze))
        self.data = mujoco.MjData(self.model)
        self.dt = self.model.opt.timestep * FRAME_SKIP
        self.action_space = gym.spaces.Box(-1.0, 1.0, (self.model.nu,), np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float64)

    def _reset_ant(self, xy) -> None:
        """D4RL's ``AntEnv.reset_model``: the initial pose plus U(-0.1, 0.1) on every position
        coordinate and N(0, 0.1^2) on every velocity, the torso moved to ``xy``."""
        mujoco, model, data = self._mujoco, self.model, self.data
        mujoco.mj_resetData(model, data)
        data.qpos[:] = model.qpos0 + self.np_random.uniform(-0.1, 0.1, model.nq)
        data.qvel[:] = 0.1 * self.np_random.standard_normal(model.nv)
        data.qpos[:2] += xy
        mujoco.mj_forward(model, data)

    def _simulate(self, action) -> None:
        self.data.ctrl[:] = TORQUE_LIMIT * np.clip(action, -1.0, 1.0)
        self._mujoco.mj_step(self.model, self.data, nstep=FRAME_SKIP)

    @property
    def xy(self) -> np.ndarray:
        return self.data.qpos[:2].copy()

    def _state(self) -> np.ndarray:
        """``qpos[:15]`` then ``qvel[:14]``: D4RL's full-position ant observation."""
        return np.concatenate([self.data.qpos[:15], self.data.qvel[:14]])

    def advance(self, action) -> np.ndarray:
        """One 0.1 s step outside any task (no reward, no end): D4RL's 29-value state after it."""
        self._simulate(action)
        return self._state()


class AntMazeEnv(_Ant):
    """The ant in one of D4RL's mazes, evaluated as D4RL's ``antmaze-*-v2``: from the start cell to
    the goal cell, reward 1 and the end of the episode once within 0.5 of the goal.

    ``reset`` draws the goal as D4RL's ``goal_sampler`` does: the goal cell's centre plus
    ``U(0, 1) + U(0, 0.5)`` per axis (so up to 1.5 m toward +x, +y; v2 redraws it every episode).
    ``options={"goal_cell": (row, col), "start_cell": (row, col)}`` choose other cells, as data
    collection will; a chosen start cell gets D4RL's multi-start noise ``U(0, 1)`` per axis.
    ``terminate_on_success=False`` keeps going after the goal (D4RL's data collection).
    """

    def __init__(self, maze: str = "umaze", terminate_on_success: bool = True):
        self.maze = mazes.get(maze)
        self.terminate_on_success = terminate_on_success
        super().__init__(self.maze)
        self.goal = self.maze.goal_xy

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        rng, scaling = self.np_random, mazes.SCALING
        goal_cell = tuple(options.get("goal_cell") or self.maze.goal_cell)
        start_cell = options.get("start_cell")
        for cell in (goal_cell, start_cell):
            if cell is not None and not self.maze.is_free(tuple(cell)):
                raise ValueError(f"{self.maze.name}: cell {tuple(cell)} is a wall")
        goal = self.maze.cell_to_xy(goal_cell) + rng.uniform(0, 0.25 * scaling, 2)
        self.goal = np.maximum(goal + rng.uniform(0, 0.5, 2) * 0.25 * scaling, 0.0)
        start = self.maze.start_xy
        if start_cell is not None:
            start = self.maze.cell_to_xy(tuple(start_cell)) + rng.uniform(0, 0.25 * scaling, 2)
        self._reset_ant(start)
        return self._state(), {"goal": self.goal.copy(), "success": False}

    def step(self, action):
        self._simulate(action)
        obs = self._state()
        success = bool(mazes.is_success(obs[:2], self.goal))
        info = {"goal": self.goal.copy(), "success": success}
        return obs, float(success), success and self.terminate_on_success, False, info


class AntDirectionEnv(_Ant):
    """The low-level task: walk in a given direction on an open plane (OGBench's ``GymXYWrapper``
    on D4RL's ant). The direction is a uniform unit vector, drawn at reset and every
    ``resample_interval`` steps; the reward is the torso's velocity along it, ``(xy' - xy) . z /
    dt`` (OGBench rewards the displacement; dividing by dt = 0.1 puts it on the scale of Gymnasium
    Ant's forward reward, for which SAC's defaults were tuned). The episode ends when the torso
    leaves D4RL's healthy height range (the ant has flipped or jumped)."""

    def __init__(self, resample_interval: int = 100):
        super().__init__(None)
        self.resample_interval = resample_interval
        self.direction = np.array([1.0, 0.0])
        self._steps = 0

    def _draw_direction(self) -> None:
        angle = self.np_random.uniform(0.0, 2.0 * np.pi)
        self.direction = np.array([np.cos(angle), np.sin(angle)])

    def _obs(self) -> np.ndarray:
        return np.concatenate([self._state()[2:], self.direction])

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._reset_ant(np.zeros(2))
        self._draw_direction()
        self._steps = 0
        return self._obs(), {"direction": self.direction.copy()}

    def step(self, action):
        before = self.xy
        self._simulate(action)
        after = self.xy
        reward = float((after - before) @ self.direction / self.dt)
        height = self.data.qpos[2]
        healthy = np.isfinite(self._state()).all() and HEALTHY_Z[0] <= height <= HEALTHY_Z[1]
        info = {"direction": self.direction.copy(), "xy": after}
        self._steps += 1
        if self._steps % self.resample_interval == 0:
            self._draw_direction()
        return self._obs(), reward, not healthy, False, info


def lowlevel_observation(maze_obs: np.ndarray, target_xy) -> np.ndarray:
    """What the direction-following policy sees in a maze: the ant's state without x, y and the
    unit vector from the torso toward ``target_xy`` (a waypoint)."""
    offset = np.asarray(target_xy, np.float64) - maze_obs[:2]
    direction = offset / max(float(np.linalg.norm(offset)), 1e-8)
    return np.concatenate([maze_obs[2:], direction])


ENV_IDS = {maze: info.env_id for maze, info in tasks.ANTMAZE_ENVS.items()}
"""The evaluation environment of each maze (play and diverse datasets share their maze's)."""
DIRECTION_ENV_ID = "eabc/AntDirection-v0"
"""The low-level training environment: ``eabc sac --env eabc/AntDirection-v0``."""


def register() -> None:
    """Put the environments in Gymnasium's registry (done on ``import eabc.data``)."""
    entry = f"{__name__}:"
    for name, env_id in ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(
                env_id,
                entry_point=entry + "AntMazeEnv",
                max_episode_steps=mazes.MAZES[name].max_episode_steps,
                kwargs={"maze": name},
            )
    if DIRECTION_ENV_ID not in gym.registry:
        gym.register(
            DIRECTION_ENV_ID, entry_point=entry + "AntDirectionEnv", max_episode_steps=1000
        )
