"""AntMaze: D4RL's mazes and coordinates, the BFS waypoint planner, relabelling, the score, and the
environments (observation layout, goal noise, termination on success, the low-level task)."""

from __future__ import annotations

import collections
import dataclasses
import itertools
import json

import gymnasium as gym
import mujoco
import numpy as np
import pytest

from eabc.data import antmaze, mazes, tasks
from eabc.data.dataset import DatasetError
from eabc.data.mazes import MAZES

R, G = "r", "g"
# D4RL's d4rl/locomotion/maze_env.py, as lists: the evaluation maps (*_TEST) and the maps its
# generation script rolled out in (U_MAZE, BIG_MAZE, HARDEST_MAZE).
D4RL_TEST = {
    "umaze": [[1, 1, 1, 1, 1], [1, R, 0, 0, 1], [1, 1, 1, 0, 1], [1, G, 0, 0, 1], [1, 1, 1, 1, 1]],
    "medium": [
        [1, 1, 1, 1, 1, 1, 1, 1], [1, R, 0, 1, 1, 0, 0, 1], [1, 0, 0, 1, 0, 0, 0, 1],
        [1, 1, 0, 0, 0, 1, 1, 1], [1, 0, 0, 1, 0, 0, 0, 1], [1, 0, 1, 0, 0, 1, 0, 1],
        [1, 0, 0, 0, 1, 0, G, 1], [1, 1, 1, 1, 1, 1, 1, 1],
    ],
    "large": [
        [1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1], [1, R, 0, 0, 0, 1, 0, 0, 0, 0, 0, 1],
        [1, 0, 1, 1, 0, 1, 0, 1, 0, 1, 0, 1], [1, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 1],
        [1, 0, 1, 1, 1, 1, 0, 1, 1, 1, 0, 1], [1, 0, 0, 1, 0, 1, 0, 0, 0, 0, 0, 1],
        [1, 1, 0, 1, 0, 1, 0, 1, 0, 1, 1, 1], [1, 0, 0, 1, 0, 0, 0, 1, 0, G, 0, 1],
        [1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1],
    ],
}  # fmt: skip
D4RL_GENERATION_GOALS = {
    "umaze": [(3, 1)],
    "medium": [(2, 6), (5, 1), (6, 5)],
    "large": [(1, 6), (3, 5), (3, 10), (5, 2), (7, 4), (7, 6), (7, 9)],
}
# Start and goal cell centres in D4RL's coordinates (x = col * 4 - 4, y = row * 4 - 4 with the
# reset cell at (1, 1)); D4RL's antmaze-*-v2 target goals lie within [0, 1.5) above these.
D4RL_START_GOAL = {
    "umaze": ((0, 0), (0, 8)),
    "medium": ((0, 0), (20, 20)),
    "large": ((0, 0), (32, 24)),
}


@pytest.mark.parametrize("name", list(MAZES))
def test_maps_cells_and_positions_are_d4rls(name):
    maze, d4rl = MAZES[name], D4RL_TEST[name]
    assert maze.shape == (len(d4rl), len(d4rl[0]))
    for (row, col), value in np.ndenumerate(np.array(d4rl, dtype=object)):
        assert maze.is_free((row, col)) == (value != 1)
        assert (maze.layout[row][col] in "RG") == (value in (R, G))
    assert maze.start_cell == (1, 1) and d4rl[1][1] == R
    assert d4rl[maze.goal_cell[0]][maze.goal_cell[1]] == G
    np.testing.assert_array_equal(maze.start_xy, D4RL_START_GOAL[name][0])
    np.testing.assert_array_equal(maze.goal_xy, D4RL_START_GOAL[name][1])
    assert list(maze.generation_goals) == D4RL_GENERATION_GOALS[name]
    assert all(maze.is_free(cell) for cell in maze.generation_goals)
    assert maze.max_episode_steps == (700 if name == "umaze" else 1000)
    for cell in maze.free_cells:  # xy_to_cell inverts cell_to_xy, anywhere inside the square
        for offset in ([0, 0], [1.99, -1.99], [-1.99, 1.99]):
            assert maze.xy_to_cell(maze.cell_to_xy(cell) + offset) == cell
    assert mazes.maze_of(f"antmaze-{name}-diverse") is maze


def test_a_bad_layout_or_name_is_refused():
    with pytest.raises(ValueError, match="exactly one 'G'"):
        mazes.Maze("x", ("###", "#R#", "###"), 10, ())
    with pytest.raises(ValueError, match="names no AntMaze maze"):
        mazes.maze_of("hopper-medium")


@pytest.mark.parametrize("name", list(MAZES))
def test_the_planner_finds_a_shortest_path_between_any_two_free_cells(name):
    maze = MAZES[name]
    for start, target in itertools.product(maze.free_cells, repeat=2):
        distance = mazes.distances_to(maze, target)
        cell, steps = start, 0
        while cell != target:
            step = mazes.next_cell(maze, cell, target)
            assert maze.is_free(step) and abs(step[0] - cell[0]) + abs(step[1] - cell[1]) == 1
            cell, steps = step, steps + 1
        assert steps == distance[start] < np.inf  # every free cell reaches every other
    with pytest.raises(ValueError, match="is a wall"):
        mazes.distances_to(maze, (0, 0))


@pytest.mark.parametrize("planner", ["waypoint", "WaypointPlanner"])
@pytest.mark.parametrize("name", list(MAZES))
def test_a_point_mass_led_by_waypoints_reaches_every_goal_and_stays_off_the_walls(name, planner):
    """A point that moves 0.5 m per step toward :func:`mazes.waypoint` or a
    :class:`mazes.WaypointPlanner` (D4RL's noise) gets within 0.5 of a noisy goal from anywhere,
    every position it passes in a free cell."""
    maze, rng = MAZES[name], np.random.default_rng(0)
    cells = maze.free_cells
    pairs = [(maze.start_cell, maze.goal_cell)] + [
        (cells[i], cells[j]) for i, j in rng.integers(0, len(cells), (60, 2))
    ]
    for start, goal_cell in pairs:
        xy = maze.cell_to_xy(start) + rng.uniform(-1.9, 1.9, 2)
        goal = maze.cell_to_xy(goal_cell) + rng.uniform(0, 1.5, 2)
        plan = mazes.WaypointPlanner(maze, goal)
        for _ in range(int(mazes.distances_to(maze, goal_cell)[start] + 2) * 16):
            if mazes.is_success(xy, goal):
                break
            target = (
                plan(xy, rng)
                if planner == "WaypointPlanner"
                else mazes.waypoint(maze, xy, goal, rng)
            )
            offset = target - xy
            xy = xy + offset * min(1.0, 0.5 / np.linalg.norm(offset))
            assert maze.is_free(maze.xy_to_cell(xy)), (start, goal_cell, xy)
        assert mazes.is_success(xy, goal), (start, goal_cell)


def test_the_planner_reaches_the_middle_of_a_cell_before_turning():
    """medium, down column 6 toward the goal cell (6, 5): the way passes the corner cell (6, 6),
    where the evaluation goal lies. The planner keeps heading into (6, 6) until the point is
    within 0.5 of the middle of its waypoints, (20.5, 20.5); only then toward (6, 5)'s goal."""
    maze, rng = MAZES["medium"], np.random.default_rng(0)
    goal = maze.cell_to_xy((6, 5)) + 0.7
    plan = mazes.WaypointPlanner(maze, goal)
    assert (plan(np.array([20.5, 16.5]), rng) >= [20.0, 20.0]).all()  # in (5, 6): on to (6, 6)
    entering = plan(np.array([20.4, 18.2]), rng)  # just inside (6, 6): its own middle first
    assert (entering >= [20.0, 20.0]).all() and (entering < [21.0, 21.0]).all()
    np.testing.assert_array_equal(plan(np.array([20.3, 20.2]), rng), goal)  # arrived: turn
    np.testing.assert_array_equal(plan(np.array([19.5, 20.6]), rng), goal)  # and stays turned
    # the stateless rule turns at the cell's edge
    np.testing.assert_array_equal(mazes.waypoint(maze, np.array([20.4, 18.2]), goal, rng), goal)


def test_relabelling_rewards_the_next_position_within_half_a_metre():
    goal = np.array([0.5, 8.5])  # offsets exact in binary: 0.5 is 0.5
    next_xy = goal + np.array([[0.25, -0.25], [0.0, 0.5], [-0.5078125, 0.0], [-3.0, 0.0]])
    rewards, terminals = mazes.relabel(next_xy, goal)
    np.testing.assert_array_equal(rewards, [1.0, 1.0, 0.0, 0.0])  # 0.5 exactly counts (D4RL <=)
    assert rewards.dtype == np.float32 and terminals.dtype == bool
    np.testing.assert_array_equal(terminals, rewards == 1)
    np.testing.assert_array_equal(mazes.training_rewards(rewards), [0.0, 0.0, -1.0, -1.0])


def test_the_score_is_100_times_the_success_rate_as_d4rls_normalisation():
    returns = [1.0, 0.0, 0.0, 1.0, 1.0]  # an AntMaze episode's return: 1 on success, else 0
    assert mazes.success_score(returns) == 60.0
    assert mazes.success_score(np.array(returns, bool)) == 60.0
    assert np.mean([tasks.normalized_score(r, 0.0, 1.0) for r in returns]) == 60.0
    with pytest.raises(ValueError, match="no episodes"):
        mazes.success_score([])


@pytest.mark.parametrize("name", list(MAZES))
def test_maze_env_is_d4rls_evaluation(name):
    env = gym.make(antmaze.ENV_IDS[name])
    assert env.spec.max_episode_steps == MAZES[name].max_episode_steps
    inner, maze = env.unwrapped, MAZES[name]
    # walls where D4RL's MazeEnv puts them: block (i, j) at (j * 4 - 4, i * 4 - 4, 1), half-size 2
    blocks = {
        inner.model.geom(g).name: (inner.model.geom_pos[g], inner.model.geom_size[g])
        for g in range(inner.model.ngeom)
        if inner.model.geom(g).name.startswith("block_")
    }
    assert len(blocks) == len(maze.wall_cells)
    for i, j in maze.wall_cells:
        pos, size = blocks[f"block_{i}_{j}"]
        np.testing.assert_allclose(pos, [j * 4 - 4, i * 4 - 4, 1.0])
        np.testing.assert_allclose(size, [2.0, 2.0, 1.0])
    obs, info = env.reset(seed=0)
    assert obs.shape == (29,) and env.observation_space.shape == (29,)
    np.testing.assert_array_equal(obs[:15], inner.data.qpos[:15])
    np.testing.assert_array_equal(obs[15:], inner.data.qvel[:14])
    assert np.abs(obs[:2] - maze.start_xy).max() <= 0.1  # D4RL's U(-0.1, 0.1) reset noise
    goals = [info["goal"]] + [env.reset()[1]["goal"] for _ in range(20)]
    offsets = np.array(goals) - maze.goal_xy
    assert (offsets >= 0).all() and (offsets < 1.5).all() and len(np.unique(offsets)) == 42
    _, reward, terminated, truncated, info = env.step(np.zeros(8))
    assert (reward, terminated, truncated, info["success"]) == (0.0, False, False, False)
    inner.data.qpos[:2] = inner.goal + [0.3, 0.0]  # carry the ant to the goal
    obs, reward, terminated, _, info = env.step(np.zeros(8))
    assert mazes.is_success(obs[:2], inner.goal)
    assert (reward, terminated, info["success"]) == (1.0, True, True)


def test_maze_env_options_and_collection_mode():
    env = antmaze.AntMazeEnv("medium", terminate_on_success=False)
    obs, info = env.reset(seed=1, options={"start_cell": (4, 5), "goal_cell": (2, 6)})
    start = MAZES["medium"].cell_to_xy((4, 5))
    assert ((obs[:2] - start) > -0.11).all() and ((obs[:2] - start) < 1.11).all()
    assert ((info["goal"] - MAZES["medium"].cell_to_xy((2, 6))) >= 0).all()
    env.data.qpos[:2] = env.goal
    _, reward, terminated, _, _ = env.step(np.zeros(8))
    assert reward == 1.0 and not terminated
    with pytest.raises(ValueError, match="is a wall"):
        env.reset(options={"goal_cell": (0, 0)})


def test_the_ant_is_d4rls_derived_from_gymnasiums_ant_xml():
    """The model built from Gymnasium's ant.xml has D4RL's physics; every number below is D4RL's
    ant.xml as MuJoCo compiles it (a policy trained on this model relies on each of them)."""
    model = antmaze.AntDirectionEnv().model
    assert model.opt.timestep == 0.02 and model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert antmaze.FRAME_SKIP == 5 and model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    np.testing.assert_array_equal(model.opt.gravity, [0.0, 0.0, -9.81])
    # motors in D4RL's order, gear 1 and ctrlrange +-30: actions in [-1, 1] are scaled by 30
    joints = [model.joint(model.actuator_trnid[i, 0]).name for i in range(model.nu)]
    assert joints == [f"{part}_{leg}" for leg in (4, 1, 2, 3) for part in ("hip", "ankle")]
    np.testing.assert_array_equal(model.actuator_gear[:, 0], np.ones(8))
    np.testing.assert_array_equal(model.actuator_ctrlrange, np.tile([-30.0, 30.0], (8, 1)))
    # joints: hips +-30 degrees, ankles 30-70 degrees (signs per leg), damping and armature 1
    hip, ankle = np.deg2rad([-30, 30]), np.deg2rad([30, 70])
    np.testing.assert_allclose(model.jnt_range[1:], [hip, ankle, hip, -ankle[::-1], hip,
                                                     -ankle[::-1], hip, ankle], rtol=1e-15)  # fmt: skip
    np.testing.assert_array_equal(model.dof_damping, [0.0] * 6 + [1.0] * 8)
    np.testing.assert_array_equal(model.dof_armature, [0.0] * 6 + [1.0] * 8)
    # density 5: a torso sphere of radius 0.25 weighs 4/3 pi 0.25^3 * 5
    assert model.body_mass[1] == pytest.approx(4 / 3 * np.pi * 0.25**3 * 5, rel=1e-12)
    assert model.body_mass.sum() == pytest.approx(0.9108800827073915, rel=1e-12)
    np.testing.assert_allclose(model.body_mass[[2, 4]], [0.03915775372846671, 0.06759220453268026])
    assert model.qpos0[2] == 0.75  # the torso starts 0.75 m up
    # contacts: D4RL's geom defaults (MuJoCo's solimp would be 0.9 0.95 0.001)
    ant = [g for g in range(model.ngeom) if model.geom(g).name != "floor"]
    np.testing.assert_array_equal(model.geom_friction[ant], np.tile([1.0, 0.5, 0.5], (len(ant), 1)))
    np.testing.assert_array_equal(model.geom_solref[ant], np.tile([0.02, 1.0], (len(ant), 1)))
    solimp = np.tile([0.8, 0.8, 0.01, 0.5, 2.0], (len(ant), 1))
    np.testing.assert_array_equal(model.geom_solimp[ant], solimp)
    np.testing.assert_array_equal(model.geom_margin[ant], np.full(len(ant), 0.01))
    assert (model.geom_condim == 3).all() and (model.geom_conaffinity[ant] == 0).all()
    env = antmaze.AntDirectionEnv()
    assert env.dt == pytest.approx(0.1)
    env.reset(seed=0)
    env.step(np.full(8, 5.0))  # out-of-range actions are clipped to [-1, 1], i.e. +-30
    np.testing.assert_array_equal(env.data.ctrl, np.full(8, 30.0))


def test_an_unexpected_gymnasium_ant_xml_is_refused(tmp_path, monkeypatch):
    (tmp_path / "ant.xml").write_text('<mujoco model="ant"><worldbody/></mujoco>')
    monkeypatch.setattr(antmaze, "gymnasium_ant_xml", lambda: tmp_path / "ant.xml")
    with pytest.raises(RuntimeError, match="Gymnasium's ant changed"):
        antmaze.model_xml()


def test_direction_env_rewards_velocity_along_its_direction():
    env = gym.make(antmaze.DIRECTION_ENV_ID)
    inner = env.unwrapped
    assert env.spec.max_episode_steps == 1000
    obs, info = env.reset(seed=3)
    assert obs.shape == (29,) and np.linalg.norm(obs[-2:]) == pytest.approx(1.0)
    np.testing.assert_array_equal(obs[:-2], np.concatenate([inner.data.qpos[2:], inner.data.qvel]))
    rng, directions = np.random.default_rng(0), [obs[-2:]]
    for step in range(1, 201):
        before = inner.data.qpos[:2].copy()
        obs, reward, terminated, _, info = env.step(rng.uniform(-1, 1, 8))
        assert reward == pytest.approx((info["xy"] - before) @ info["direction"] / 0.1)
        assert not terminated
        if step % 100 == 0:
            directions.append(obs[-2:])
    assert not np.allclose(directions[0], directions[1])  # redrawn every 100 steps
    inner.data.qpos[2] = 1.5  # thrown up: out of D4RL's healthy height range
    assert env.step(np.zeros(8))[2]


def test_lowlevel_observation_points_at_the_waypoint():
    obs = np.arange(29, dtype=np.float64)
    low = antmaze.lowlevel_observation(obs, obs[:2] + [3.0, -4.0])
    np.testing.assert_array_equal(low[:27], obs[2:])
    np.testing.assert_allclose(low[27:], [0.6, -0.8])


# The waypoint controller and the datasets it makes.


@pytest.fixture(scope="module")
def policy():
    from eabc.data import antmaze_collect

    return antmaze_collect.load_policy()[0]


def test_episode_cells_follow_each_family():
    from eabc.data.antmaze_collect import episode_cells

    rng = np.random.default_rng(0)
    for maze in MAZES.values():
        assert episode_cells(maze, "fixed", rng) == (None, maze.goal_cell)
        for _ in range(50):
            start, goal = episode_cells(maze, "diverse", rng)
            assert start != goal and maze.is_free(start) and maze.is_free(goal)
            start, goal = episode_cells(maze, "play", rng)
            assert start in (maze.start_cell, *maze.generation_goals)
            assert goal in maze.generation_goals and goal != start
    with pytest.raises(ValueError, match="unknown AntMaze family 'random'"):
        episode_cells(MAZES["umaze"], "random", rng)


def test_faithful_episode_cells_follow_d4rls_dataset_flags():
    """D4RL's files name their flags: umaze from the start cell to the map's goal cell; play
    (--multi_start) from any free cell but a goal cell, uniformly, to a goal cell of the map its
    script rolled out in; diverse (--multi_start --multigoal) start and goal uniform over the free
    cells."""
    from eabc.data.antmaze_collect import d4rl_episode_cells

    rng = np.random.default_rng(0)
    for maze in MAZES.values():
        assert d4rl_episode_cells(maze, "fixed", rng) == (None, maze.goal_cell)
        play = [d4rl_episode_cells(maze, "play", rng) for _ in range(3000)]
        starts = collections.Counter(start for start, _ in play)
        assert set(starts) == set(maze.free_cells) - set(maze.generation_goals)
        assert max(starts.values()) < 2 * min(starts.values())  # spread evenly
        assert {goal for _, goal in play} == set(maze.generation_goals)
        diverse = [d4rl_episode_cells(maze, "diverse", rng) for _ in range(3000)]
        assert (
            {start for start, _ in diverse} == {goal for _, goal in diverse} == set(maze.free_cells)
        )
    with pytest.raises(ValueError, match="unknown AntMaze family 'random'"):
        d4rl_episode_cells(MAZES["umaze"], "random", rng)


def test_faithful_actions_are_sampled_from_the_policy_not_its_mean(policy):
    """D4RL sampled its SAC policy's tanh-Gaussian (rlkit's exploration policy); the first recipe
    took the mean action. Each row draws from its episode's own generator."""
    from eabc import numpy_networks
    from eabc.data.antmaze_collect import _actions

    obs = np.random.default_rng(0).standard_normal((4, 29))
    rngs = lambda seed: [np.random.default_rng([seed, k]) for k in range(4)]  # noqa: E731
    sampled = _actions(policy, True)(obs, rngs(1))
    mean, log_std = np.split(numpy_networks.numpy_mlp(policy)(obs).astype(np.float64), 2, axis=1)
    eps = np.stack([r.standard_normal(8) for r in rngs(1)])
    std = np.exp(np.clip(log_std, numpy_networks.LOG_STD_MIN, numpy_networks.LOG_STD_MAX))
    np.testing.assert_allclose(sampled, np.tanh(mean + std * eps), rtol=1e-12)
    np.testing.assert_array_equal(_actions(policy, True)(obs, rngs(1)), sampled)
    assert not np.allclose(_actions(policy, True)(obs, rngs(2)), sampled)
    mean_action = numpy_networks.numpy_actor(policy, 1.0, gaussian=True)(obs)
    np.testing.assert_array_equal(_actions(policy, False)(obs, rngs(1)), mean_action)
    assert np.abs(sampled - mean_action).mean() > 0.05


def test_d4rls_cell_lookup_truncates_toward_the_next_centre():
    maze = MAZES["umaze"]
    assert mazes.d4rl_cell(maze, (-1.9, -1.9)) == (1, 1)  # raised to 1e-4
    assert mazes.d4rl_cell(maze, (3.99, 0.0)) == (1, 1)  # the right half of (1, 1) and ...
    assert mazes.d4rl_cell(maze, (5.0, 0.0)) == (1, 2)  # ... the left half of (1, 2)
    assert mazes.d4rl_cell(maze, (0.5, 7.5)) == (2, 1)  # (3, 1)'s lower half: a wall cell
    assert maze.xy_to_cell((0.5, 7.5)) == (3, 1)


@pytest.mark.parametrize("name", list(MAZES))
def test_d4rls_waypoint_rule_steps_along_a_shortest_path_from_every_position(name):
    """From positions all over every free cell (also where the lookup puts the torso in a wall
    cell) toward random noisy goals: the goal itself, or a fresh point in a free cell one step
    nearer the goal's cell than the looked-up cell."""
    maze, rng = MAZES[name], np.random.default_rng(0)
    cells = maze.free_cells
    offsets = np.linspace(-1.9, 1.9, 5)
    for cell in cells:
        for dx, dy in itertools.product(offsets, offsets):
            xy = maze.cell_to_xy(cell) + [dx, dy]
            goal_cell = cells[rng.integers(len(cells))]
            goal = maze.cell_to_xy(goal_cell) + rng.uniform(0, 1.5, 2)
            point = mazes.d4rl_waypoint(maze, xy, goal, rng)
            if np.array_equal(point, goal):
                continue
            step, here = maze.xy_to_cell(point), mazes.d4rl_cell(maze, xy)
            distance = mazes.distances_to(maze, goal_cell)
            offset = point - maze.cell_to_xy(step)
            assert maze.is_free(step) and (offset >= 0).all() and (offset < 1).all()
            if maze.is_free(here):
                assert distance[step] == distance[here] - 1, (xy, goal)
            again = mazes.d4rl_waypoint(maze, xy, goal, rng)
            assert maze.xy_to_cell(again) == step and not np.array_equal(again, point)


def test_the_first_recipe_stays_makeable_and_loadable_by_name(tmp_path, monkeypatch, policy):
    """``antmaze-umaze@planner-v0`` makes the first recipe, its arrays bit for bit as before
    recipes had names; a cached file from then (no recipe recorded) is not taken for the default
    recipe's, and is kept under its recipe's name rather than overwritten."""
    import hashlib

    from eabc.data import antmaze_collect, generate, hdf5_writer, loaders

    assert "antmaze-umaze@planner-v0" in generate.builtin_names()
    assert antmaze_collect.split_name("antmaze-umaze") == ("antmaze-umaze", "faithful-v1")
    with pytest.raises(DatasetError, match="unknown AntMaze recipe 'v9'; the recipes are"):
        antmaze_collect.split_name("antmaze-umaze@v9")
    # the first recipe's controller, as recorded before recipes had names
    collected = antmaze_collect.collect(
        "umaze", "fixed", 4, seed=5, actor=policy, max_episode_steps=60, num_envs=2,
        progress=False, recipe_name="planner-v0",
    )  # fmt: skip
    digest = hashlib.sha256()
    for array in (collected.observations, collected.actions, collected.next_observations,
                  collected.goals, collected.success, collected.flipped):  # fmt: skip
        digest.update(np.ascontiguousarray(array).tobytes())
    assert digest.hexdigest()[:16] == "143c0b343e76567e"

    monkeypatch.setattr(antmaze_collect, "NUM_ENVS", 2)
    cache = tmp_path / "datasets"
    old = generate.make("antmaze-umaze@planner-v0", cache / "old.hdf5", seed=1, size=800)
    data = loaders.load_file(old)
    np.testing.assert_array_equal(np.flatnonzero(data.timeouts), [699, 799])  # 700-step episodes
    assert data.metadata["antmaze_recipe"] == "planner-v0" and data.reward_offset == -1.0
    # a cache from before recipes: the same file under the plain name, no recipe recorded
    metadata = {k: v for k, v in data.metadata.items() if k != "antmaze_recipe"}
    plain = hdf5_writer.save_hdf5(
        dataclasses.replace(data, name="antmaze-umaze", metadata=metadata),
        cache / "antmaze-umaze.hdf5",
    )
    assert not generate.is_current(plain, "antmaze-umaze")  # the default recipe makes it again
    assert generate.is_current(plain, "antmaze-umaze@planner-v0")
    loaded = generate.load_or_make("antmaze-umaze@planner-v0", cache_dir=tmp_path)
    assert loaded.fingerprint() == data.fingerprint() and not plain.exists()  # moved, not made
    moved = cache / "antmaze-umaze@planner-v0.hdf5"
    plain.write_bytes(moved.read_bytes())
    moved.unlink()
    assert generate.keep_other_recipe(plain, "antmaze-umaze") == moved
    assert not plain.exists() and loaders.load_file(moved).fingerprint() == data.fingerprint()


def test_the_controller_takes_the_ant_to_the_umaze_goal(policy):
    """The zoo's low-level policy, steered by the waypoints with the data's action noise, reaches
    the evaluation goal from the start in most episodes (the card measures 30 per maze)."""
    from eabc.data import antmaze_collect

    collected = antmaze_collect.collect(
        "umaze", "fixed", 10, seed=0, actor=policy, recipe_name="planner-v0"
    )
    assert collected.success.sum() >= 6, collected.summary()
    assert collected.observations.shape == (7000, 29) and collected.actions.shape == (7000, 8)
    assert np.abs(collected.actions).max() <= 1.0
    goals = collected.goals - MAZES["umaze"].goal_xy  # D4RL's goal noise, per episode
    assert (goals >= 0).all() and (goals < 1.5).all() and len(np.unique(goals)) == 20


def test_upside_down_reads_the_torsos_quaternion():
    from eabc.data.antmaze_collect import upside_down

    def about_x(degrees):
        half = np.radians(degrees) / 2
        return [np.cos(half), np.sin(half), 0, 0]

    obs = np.zeros((5, 29))
    obs[:, 3:7] = [[1, 0, 0, 0], about_x(180), about_x(80), about_x(100), [0.5, 0.5, 0.5, 0.5]]
    # upright; rolled over; tilted 80 and 100 degrees; 120 degrees about (1, 1, 1): z axis -> x axis
    assert upside_down(obs).tolist() == [False, True, False, True, False]
    obs[1, 3:7] = [0, 0, 1, 0]  # 180 degrees about y
    assert upside_down(obs[1])


def test_the_policy_alone_walks_to_goals_on_the_open_plane(policy):
    """The card's open-plane measurement: the zoo's policy reaches goals 5-10 m away; an actor
    that outputs nothing but the noise does not."""
    from eabc.data import antmaze_collect

    walked = antmaze_collect.open_plane(policy, 4, seed=0)
    assert walked["success_rate"] >= 0.75 and walked["flip_rate"] <= 0.25, walked
    assert 25 <= walked["median_steps_to_goal"] <= 200  # 5-10 m at 0.5-2 m/s, 0.1 s per step
    still = {k: np.zeros_like(v) for k, v in policy.items()}
    stood = antmaze_collect.open_plane(still, 2, seed=0, steps=100)
    assert stood["success_rate"] == 0.0 and stood["median_steps_to_goal"] is None


def test_zoo_build_antmaze_writes_the_policy_and_its_measured_card(tmp_path, monkeypatch):
    """`eabc zoo build RUN antmaze` from a (very short) SAC run on the direction task: the actor in
    float16, the card with the run's settings and the controller's and open plane's rates."""
    from eabc.data import antmaze_collect, zoo
    from eabc.training import online, zoo_build

    config = online.SACTrainConfig(
        env="eabc/AntDirection-v0", steps=600, start_steps=500, update_every=50, batch_size=64,
        eval_interval=300, snapshot_interval=300, checkpoint_interval=300, eval_episodes=1,
    )  # fmt: skip
    run = online.start_sac(config, tmp_path / "run")
    online.train_sac(run, progress=False)
    monkeypatch.setattr(antmaze_collect, "NUM_ENVS", 2)
    card = zoo_build.build_antmaze(
        tmp_path / "run", tmp_path / "zoo", episodes=2, log=print, plane_episodes=2
    )
    assert card == json.loads((tmp_path / "zoo" / "antmaze" / zoo.CARD).read_text())
    assert card["training_steps"] == 600 and card["direction_return"]["step"] == 600
    assert set(card["controller"]) == {"what", "umaze", "medium", "large"}
    assert all(card["controller"][m]["episodes"] == 2 for m in ("umaze", "medium", "large"))
    assert card["open_plane"]["episodes"] == 2 and 0 <= card["open_plane"]["success_rate"] <= 1
    actor, read = antmaze_collect.load_policy(tmp_path / "zoo")
    assert read == card and all(v.dtype == np.float16 for v in np.load(
        antmaze_collect.policy_path(tmp_path / "zoo")).values())  # fmt: skip
    with pytest.raises(DatasetError, match="has no actor snapshot 123"):
        zoo_build.build_antmaze(tmp_path / "run", tmp_path / "zoo", step=123)


@pytest.fixture(scope="module")
def made(tmp_path_factory, policy):
    """antmaze-umaze-diverse of 1,500 transitions (by the default recipe: one whole 1,001-step
    episode and a cut one), made twice with seed 3 and once with seed 4 (2 environments at a time
    instead of 10: seconds, not a minute)."""
    from eabc.data import antmaze_collect, generate

    root = tmp_path_factory.mktemp("antmaze")
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(antmaze_collect, "NUM_ENVS", 2)
        paths = [
            generate.make("antmaze-umaze-diverse", root / f"{i}.hdf5", seed=seed, size=1500)
            for i, seed in enumerate((3, 3, 4))
        ]
    return paths


def test_made_antmaze_dataset_has_d4rls_layout_rewards_and_settings(made):
    from eabc.data import antmaze_collect, describe, generate, loaders

    data = loaders.load_file(made[0])
    assert data.size == 1500 and data.obs_dim == 29 and data.act_dim == 8
    # the dataset's own settings: evaluation env, reference scores 0 and 1, training on r - 1
    assert data.env_id == "eabc/AntMaze-UMaze-v0" and data.name == "antmaze-umaze-diverse"
    assert (data.ref_min_score, data.ref_max_score, data.reward_offset) == (0.0, 1.0, -1.0)
    np.testing.assert_array_equal(data.training_view().rewards, data.rewards - 1.0)
    # relabelled: 1 (and a terminal) where the next position is within 0.5 of the evaluation goal
    goal = MAZES["umaze"].goal_xy + 0.75
    expected = np.linalg.norm(data.next_observations[:, :2] - goal, axis=1) <= 0.5
    np.testing.assert_array_equal(data.rewards, expected.astype(np.float32))
    np.testing.assert_array_equal(data.terminals, expected)
    # whole 1,001-step episodes (D4RL's script), each ending in a timeout; the budget cuts the
    # second one
    np.testing.assert_array_equal(np.flatnonzero(data.timeouts), [1000, 1499])
    np.testing.assert_array_equal(data.observations[1:1001], data.next_observations[:1000])
    assert not np.array_equal(data.observations[1001], data.next_observations[1000])
    controller = data.metadata["controller"]
    assert controller["family"] == "diverse" and controller["episodes"] == 2
    assert data.metadata["antmaze_recipe"] == controller["recipe"]["name"] == "faithful-v1"
    info = describe.describe_dataset(data)["antmaze"]
    assert info["reward_1_transitions"] == int(expected.sum())
    assert info["position_jumps_without_timeout"]["count"] == 0
    assert info["controller_success_rate"] == controller["success_rate"]
    assert generate.is_current(made[0], "antmaze-umaze-diverse")
    # a jump inside an episode is found
    moved = data.observations.copy()
    moved[300, :2] += 5.0
    jumped = antmaze_collect.position_jumps(dataclasses.replace(data, observations=moved))
    assert jumped["count"] == 2 and jumped["first_rows"] == [299, 300]


def test_made_antmaze_dataset_is_deterministic_for_a_seed(made):
    from eabc.data import loaders

    first, again, other = (loaders.load_file(p) for p in made)
    assert first.fingerprint() == again.fingerprint() != other.fingerprint()


def test_coverage_plot_is_drawn_for_antmaze_data_only(made, tmp_path):
    from eabc.data import antmaze_collect, loaders

    data = loaders.load_file(made[0])
    path = antmaze_collect.plot_coverage(data, tmp_path / "cover.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(DatasetError, match="draws AntMaze data over its maze"):
        antmaze_collect.plot_coverage(dataclasses.replace(data, env_id="Hopper-v4"), path)


def test_each_reward_convention_is_applied_and_each_algorithm_has_its_published_default(made):
    """minus-one trains on r - 1, raw on the stored 0/1, iql-scale on 0/1 times 1000 / (max - min
    episode return); unset, IQL (its train_offline.py) takes r - 1 and TD3+BC and EABC (the
    authors' TD3_BC code) the raw rewards. MuJoCo data keep the algorithm's own preprocessing."""
    from eabc.agents import get_algorithm
    from eabc.data import loaders
    from eabc.training import rewards
    from eabc.training.config import TrainConfig
    from eabc.training.lifecycle import prepared

    data = loaders.load_file(made[0])
    goal_reached = (np.arange(data.size) % 9 == 0) & (np.arange(data.size) < 1200)
    data = dataclasses.replace(data, rewards=goal_reached.astype(np.float32))  # returns differ
    iql = get_algorithm("iql")
    np.testing.assert_array_equal(prepared(iql, data, "minus-one").rewards, data.rewards - 1)
    np.testing.assert_array_equal(prepared(iql, data, "raw").rewards, data.rewards)
    returns = data.episode_returns()
    scaled = prepared(iql, data, "iql-scale")
    np.testing.assert_allclose(
        scaled.rewards, data.rewards * 1000 / (returns.max() - returns.min()), rtol=1e-6
    )
    defaults = {"iql": "minus-one", "td3bc": "raw", "eabc": "raw", "bc": "raw", "cql": "minus-one"}
    for algo, convention in defaults.items():
        assert TrainConfig(dataset="x", algo=algo).reward_convention == convention
        expected = data.rewards - 1 if convention == "minus-one" else data.rewards
        np.testing.assert_array_equal(prepared(get_algorithm(algo), data).rewards, expected)
    assert TrainConfig(algo="td3bc", reward_convention="minus-one").reward_convention == "minus-one"
    with pytest.raises(ValueError, match="reward_convention must be one of minus-one, raw"):
        rewards.check("r-1")
    hopper = dataclasses.replace(data, reward_offset=None)
    assert prepared(iql, hopper, "raw").metadata.get("reward_scale") is not None


def test_a_run_records_its_reward_convention_and_an_older_run_resumes_on_r_minus_1(made, tmp_path):
    """config.json says which convention a run trained on; a config.json from before the setting
    (none recorded) resumes on r - 1, what every run trained on then."""
    from eabc.training import lifecycle
    from eabc.training.config import TrainConfig

    config = TrainConfig(
        dataset=str(made[0]), algo="td3bc", steps=2, eval_interval=2, log_interval=1,
        checkpoint_interval=2, eval_episodes=1,
    )  # fmt: skip
    lifecycle.start(config, tmp_path / "run").lock.release()
    path = tmp_path / "run" / "config.json"
    saved = json.loads(path.read_text())
    assert saved["train"]["reward_convention"] == "raw"
    del saved["train"]["reward_convention"]
    path.write_text(json.dumps(saved))
    resumed = lifecycle.resume(tmp_path / "run")
    resumed.lock.release()
    assert resumed.config.reward_convention == "minus-one"


def test_antmaze_names_settings_and_errors(made):
    from eabc.agents import eabc
    from eabc.data import generate, loaders
    from eabc.evaluation import check_spaces, make_env

    assert tasks.parse_task("antmaze-medium-play-v2") == ("antmaze", "medium-play")
    assert tasks.parse_task("D4RL/antmaze/umaze-v1") == ("antmaze", "umaze")
    table5 = {"umaze": 1.0, "umaze-diverse": 0.5, "medium-diverse": 0.75, "medium-play": 1.0,
              "large-diverse": 1.0, "large-play": 1.0}  # fmt: skip
    for kind, p in table5.items():
        assert eabc.CONFIDENCE_LEVEL[("antmaze", kind)] == p
        assert f"antmaze-{kind}" in generate.builtin_names()
    # a D4RL file under its own name gets the AntMaze settings without attributes
    assert tasks.env_info(("antmaze", "large-diverse")).env_id == "eabc/AntMaze-Large-v0"
    with pytest.raises(DatasetError, match=r"did you mean antmaze-umaze-diverse\?"):
        generate.make("antmaze-umaze-divers", "unused.hdf5")
    with pytest.raises(ValueError, match="unknown maze 'tiny'; the mazes are umaze, medium, large"):
        antmaze.AntMazeEnv("tiny")
    with pytest.raises(DatasetError, match="is AntMaze data, evaluated on eabc/AntMaze-UMaze-v0"):
        check_spaces(make_env("Hopper-v4"), loaders.load_file(made[0]))


def test_table5_preset_is_the_papers_antmaze_grid_and_table1_keeps_to_mujoco():
    from eabc.experiments.presets import PRESETS
    from eabc.experiments.spec import expand

    runs = expand(PRESETS["table5"])
    assert {r.dataset for r in runs} == {f"antmaze-{kind}" for kind in tasks.ANTMAZE_KINDS}
    assert {r.algo for r in runs} == {"td3bc", "eabc"} and {r.seed for r in runs} == set(range(5))
    assert runs[0].train_config().steps == 1_000_000
    for name in ("table1", "table6", "ablation-k", "ablation-p", "ablation-pess"):
        datasets = {r.dataset for r in expand(PRESETS[name])}
        assert len(datasets) == 15 and not any(d.startswith("antmaze") for d in datasets), name


def test_reports_lay_antmaze_out_as_table5():
    import pandas as pd

    from eabc.experiments.labels import dataset_names, paper_table

    names = [f"antmaze-{kind}" for kind in reversed(tasks.ANTMAZE_KINDS)] + ["hopper-medium"]
    assert dataset_names(pd.DataFrame({"dataset": names})) == [
        "hopper-medium",
        *(f"antmaze-{kind}" for kind in tasks.ANTMAZE_KINDS),
    ]
    assert paper_table(names[:-1]).startswith("Table 5") and paper_table(names) == "Table 1"


# Learning on a tiny maze: AntMaze's pipeline with a point mass for a body.

IQL_TINY_MAZE = {
    "expectile": 0.9,  # IQL's AntMaze settings (its authors' antmaze_config.py)
    "temperature": 10.0,
    "actor_lr": 1e-3,  # tiny-test settings, so the value reaches the start in seconds
    "critic_lr": 1e-3,
    "value_lr": 1e-3,
    "tau": 0.02,
    "discount": 0.95,
}


def test_iql_learns_the_umaze_from_diverse_data_through_antmazes_pipeline(tmp_path):
    """AntMaze's pipeline end to end, on a point mass in D4RL's U-maze (tests/pointmaze.py): data
    of the noisy BFS-planner controller with umaze-diverse's random starts and goals, relabelled
    by ``mazes.relabel`` against ``relabel_goal`` (reward 1 and a terminal within 0.5 of the
    evaluation goal; every episode ends in a timeout), written in the AntMaze datasets' HDF5 layout
    with their settings, read back by ``load_file``, trained by the real trainer on ``r - 1`` and
    scored by the evaluator as 100 x the success rate. IQL (with its authors' AntMaze expectile
    and temperature) goes from 0 to 100 within 6,000 updates; BC, which ignores the rewards, stays
    at 0 on the same data, so the success comes from the rewards.

    It fails when the conventions are wrong. Measured with this seed (IQL's scores at 1,000 ...
    6,000 steps all 0 instead of 0, 0, 0, 80, 100, 100): rewards relabelled against the start's
    goal instead; a reward offset of 0, of +1 or none (IQL's MuJoCo return scaling); timeouts
    made terminals; no terminal at the goal. Seeds 0-5: the mean of the last two evaluations is
    60-100. Tiny settings, as the other learning tests: 64-64 networks, learning rates 1e-3, the
    targets' Polyak rate 0.02 and discount 0.95 (12 steps from the start to the goal at 2 m per
    step), so that the value reaches the start within the run. TD3+BC learns it too, but more
    slowly and less steadily (0 up to 4,000 steps, then 50, 0, 70, 70)."""
    import pointmaze

    from eabc.data import antmaze_collect, loaders
    from eabc.training import lifecycle, trainer
    from eabc.training.config import TrainConfig

    pointmaze.register()
    path = pointmaze.make_dataset(tmp_path / "pointmaze-umaze-diverse.hdf5", episodes=300, seed=0)
    data = loaders.load_file(path)
    assert (data.env_id, data.ref_min_score, data.ref_max_score) == (pointmaze.ENV_ID, 0.0, 1.0)
    assert data.reward_offset == -1.0 and data.size == 300 * pointmaze.MAX_EPISODE_STEPS
    goal = antmaze_collect.relabel_goal(MAZES["umaze"])
    near = np.linalg.norm(data.next_observations - goal, axis=1) <= mazes.GOAL_TOLERANCE
    np.testing.assert_array_equal(data.rewards, near.astype(np.float32))
    np.testing.assert_array_equal(data.terminals, near)
    assert 0 < near.sum() < 0.1 * data.size and data.timeouts.sum() == 300

    def train(algo: str, steps: int, overrides: dict) -> tuple[float, dict[int, float]]:
        config = TrainConfig(
            dataset=str(path),
            algo=algo,
            steps=steps,
            log_interval=1000,
            eval_interval=1000,
            checkpoint_interval=steps,
            eval_episodes=10,
        )
        run = lifecycle.start(config, tmp_path / algo, {"hidden_dims": (64, 64), **overrides}, data)
        untrained = trainer.evaluate(run)["score"]
        trainer.train(run, progress=False)
        return untrained, {int(s): e["score"] for s, e in run.state["evaluations"].items()}

    untrained, scores = train("iql", 6000, IQL_TINY_MAZE)
    assert untrained == 0.0, untrained
    assert all(score % 10 == 0 for score in scores.values())  # 100 x successes of 10 episodes
    assert np.mean([scores[5000], scores[6000]]) >= 50.0, scores
    _, bc_scores = train("bc", 2000, {})
    assert max(bc_scores.values()) == 0.0, bc_scores


# Minari's AntMaze data (Gymnasium-Robotics' AntMaze_*-v4): refused in one line.


def _goal_dict_episodes(rng: np.random.Generator, episodes: int = 2, steps: int = 5) -> list:
    """Episodes shaped as Minari's D4RL/antmaze datasets: Gymnasium-Robotics' goal dicts of the
    ant's 27 numbers without x, y (``qpos[2:15]``, ``qvel[:14]``), its x, y and the goal."""
    from minari.data_collector import EpisodeBuffer

    return [
        EpisodeBuffer(
            observations={
                "observation": rng.normal(size=(steps + 1, 27)),
                "achieved_goal": rng.normal(size=(steps + 1, 2)),
                "desired_goal": np.tile([4.2, -3.9], (steps + 1, 1)),
            },
            actions=rng.uniform(-1, 1, (steps, 8)).astype(np.float32),
            rewards=np.zeros(steps),
            terminations=np.zeros(steps, bool),
            truncations=np.r_[np.zeros(steps - 1, bool), True],
        )
        for _ in range(episodes)
    ]


def test_minari_antmaze_data_are_refused_in_one_line_that_says_what_to_use(
    tmp_path, monkeypatch, made
):
    """Minari's AntMaze data were recorded on Gymnasium-Robotics' AntMaze: Gymnasium's ant (gear
    150, 0.05 s steps) in a frame mirrored against D4RL's. No map takes them onto the evaluation
    environments (docs/datasets.md), so they are refused, with or without the minari package;
    other goal-dict data are told to flatten; our own exports (flat) load as before."""
    import sys

    import minari
    from gymnasium import spaces

    from eabc.cli import main
    from eabc.data import loaders
    from eabc.data.sources import load_dataset

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    box = lambda n: spaces.Box(-np.inf, np.inf, (n,), np.float64)  # noqa: E731
    goal_dict = spaces.Dict(
        {"observation": box(27), "achieved_goal": box(2), "desired_goal": box(2)}
    )
    rng = np.random.default_rng(0)
    for dataset_id in ("D4RL/antmaze/umaze-v1", "mine/antmaze/medium-play-v0", "mine/reach-v0"):
        with pytest.warns(UserWarning):  # Minari asks for an author's e-mail and code link
            minari.create_dataset_from_buffers(
                dataset_id,
                _goal_dict_episodes(rng),
                observation_space=goal_dict,
                action_space=spaces.Box(-1, 1, (8,), np.float32),
                algorithm_name="test",
                author="test",
            )
    refusal = (
        r"^minari:{id} was recorded on Gymnasium-Robotics' AntMaze \(goal-dict observations of "
        r"Gymnasium's ant: .*\), which eabc cannot evaluate: .*D4RL's HDF5 file \({name}-v2\.hdf5\)"
        r" or make the data here: eabc data make {name}$"
    )
    with pytest.raises(DatasetError, match=refusal.format(id="mine/antmaze/medium-play-v0",
                                                          name="antmaze-medium-play")):  # fmt: skip
        load_dataset("minari:mine/antmaze/medium-play-v0")
    with pytest.raises(SystemExit) as error:
        main(["data", "info", "minari:D4RL/antmaze/umaze-v1"])
    line = str(error.value.code)
    assert "\n" not in line and line.startswith("error: minari:D4RL/antmaze/umaze-v1 was recorded")
    assert line.endswith("eabc data make antmaze-umaze")
    with pytest.raises(DatasetError, match=r"not one flat vector per step; .*flatten them"):
        load_dataset("minari:mine/reach-v0")
    ours = loaders.load_file(made[0])  # exported by eabc: D4RL's 29 numbers, in D4RL's frame
    loaders.export_minari(ours, "eabc/antmaze/umaze-diverse-v0")
    back = load_dataset("minari:eabc/antmaze/umaze-diverse-v0")
    np.testing.assert_array_equal(back.observations, ours.observations)
    assert (back.env_id, back.reward_offset) == ("eabc/AntMaze-UMaze-v0", -1.0)

    monkeypatch.setitem(sys.modules, "minari", None)  # as if the minari extra were not installed
    with pytest.raises(DatasetError, match=refusal.format(id="D4RL/antmaze/large-diverse-v1",
                                                          name="antmaze-large-diverse")):  # fmt: skip
        load_dataset("minari:D4RL/antmaze/large-diverse-v1")
    with pytest.raises(DatasetError, match=r"^minari:eabc/antmaze/umaze-v0 needs the minari "):
        load_dataset("minari:eabc/antmaze/umaze-v0")


def test_a_sweep_naming_minari_antmaze_data_is_refused_before_it_starts(tmp_path):
    """The sweep checks its datasets before its first run: a Minari AntMaze id in the spec is
    refused with the loader's line, and the root is not even made."""
    from eabc.cli import main  # noqa: PLC0415

    spec = tmp_path / "spec.yaml"
    spec.write_text(
        'datasets: [hopper-medium, "minari:D4RL/antmaze/umaze-v1"]\nalgos: [td3bc]\nseeds: [0]\n'
    )
    root = tmp_path / "root"
    with pytest.raises(SystemExit) as error:
        main(["sweep", str(spec), "--root", str(root), "--dry-run"])
    line = str(error.value.code)
    assert "\n" not in line and line.startswith("error: minari:D4RL/antmaze/umaze-v1 was recorded")
    assert not root.exists()
