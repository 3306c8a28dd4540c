"""D4RL's AntMaze mazes as data, their geometry, the BFS waypoint planner, reward relabelling and
the success-rate score. Pure NumPy: no simulator here (the environments are :mod:`eabc.data.antmaze`).

Coordinates are D4RL's (``d4rl/locomotion/maze_env.py``): cell ``(row, col)`` has its centre at
``x = col * 4 - torso_x``, ``y = row * 4 - torso_y``, where ``(torso_x, torso_y)`` is the reset
cell's ``(col * 4, row * 4)``, so the ant starts at the origin; ``x`` grows with the column and
``y`` with the row. Every cell is a 4 x 4 square (``maze_size_scaling`` 4) and walls are whole cells.
"""

from __future__ import annotations

import dataclasses
import functools
from collections import deque

import numpy as np

SCALING = 4.0
"""D4RL's ``maze_size_scaling``: the side of a cell in metres."""
GOAL_TOLERANCE = 0.5
"""An xy position within this distance of the goal is a success (D4RL's sparse reward and relabelling)."""

Cell = tuple[int, int]


@dataclasses.dataclass(frozen=True)
class Maze:
    """One of D4RL's maps: ``#`` a wall, ``.`` free, ``R`` the reset (start) cell, ``G`` the goal."""

    name: str
    layout: tuple[str, ...]
    """Rows of the evaluation map (D4RL's ``*_TEST`` maps), top row first."""
    max_episode_steps: int
    """D4RL's time limit of the evaluation episodes (and of the data's episodes)."""
    generation_goals: tuple[Cell, ...]
    """The goal cells of the map D4RL's generation script rolled out in (``U_MAZE``, ``BIG_MAZE``,
    ``HARDEST_MAZE``). The evaluation goal is one of them for umaze and large; medium's, ``(6, 6)``,
    lies next to ``(6, 5)``."""

    def __post_init__(self):
        if len({len(row) for row in self.layout}) != 1:
            raise ValueError(f"{self.name}: the rows of the layout differ in length")
        for mark in "RG":
            if sum(row.count(mark) for row in self.layout) != 1:
                raise ValueError(f"{self.name}: the layout needs exactly one {mark!r} cell")

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.layout), len(self.layout[0])

    def _find(self, mark: str) -> Cell:
        return next((r, row.index(mark)) for r, row in enumerate(self.layout) if mark in row)

    @property
    def start_cell(self) -> Cell:
        return self._find("R")

    @property
    def goal_cell(self) -> Cell:
        return self._find("G")

    def is_free(self, cell: Cell) -> bool:
        row, col = cell
        rows, cols = self.shape
        return 0 <= row < rows and 0 <= col < cols and self.layout[row][col] != "#"

    @property
    def free_cells(self) -> list[Cell]:
        rows, cols = self.shape
        return [(r, c) for r in range(rows) for c in range(cols) if self.is_free((r, c))]

    @property
    def wall_cells(self) -> list[Cell]:
        rows, cols = self.shape
        return [(r, c) for r in range(rows) for c in range(cols) if not self.is_free((r, c))]

    @property
    def origin(self) -> np.ndarray:
        """D4RL's ``(torso_x, torso_y)``: the start cell's corner offset, subtracted everywhere."""
        row, col = self.start_cell
        return np.array([col * SCALING, row * SCALING])

    def cell_to_xy(self, cell: Cell) -> np.ndarray:
        """The centre of ``cell`` in D4RL's world coordinates."""
        row, col = cell
        return np.array([col * SCALING, row * SCALING]) - self.origin

    def xy_to_cell(self, xy) -> Cell:
        """The cell whose square holds ``xy``.

        D4RL's ``_xy_to_rowcol`` truncates instead (``int(1 + y / 4)``), which puts the second half
        of every cell into its neighbour and works only for a start cell at ``(1, 1)``; the planner
        here uses the cell the point is actually in.
        """
        col, row = np.floor((np.asarray(xy, np.float64) + self.origin) / SCALING + 0.5)
        return int(row), int(col)

    @property
    def start_xy(self) -> np.ndarray:
        return self.cell_to_xy(self.start_cell)

    @property
    def goal_xy(self) -> np.ndarray:
        """The goal cell's centre; evaluation episodes add noise to it at every reset."""
        return self.cell_to_xy(self.goal_cell)


MAZES: dict[str, Maze] = {
    "umaze": Maze(
        "umaze",
        ("#####",
         "#R..#",
         "###.#",
         "#G..#",
         "#####"),
        max_episode_steps=700,
        generation_goals=((3, 1),),
    ),
    "medium": Maze(
        "medium",
        ("########",
         "#R.##..#",
         "#..#...#",
         "##...###",
         "#..#...#",
         "#.#..#.#",
         "#...#.G#",
         "########"),
        max_episode_steps=1000,
        generation_goals=((2, 6), (5, 1), (6, 5)),
    ),
    "large": Maze(
        "large",
        ("############",
         "#R...#.....#",
         "#.##.#.#.#.#",
         "#......#...#",
         "#.####.###.#",
         "#..#.#.....#",
         "##.#.#.#.###",
         "#..#...#.G.#",
         "############"),
        max_episode_steps=1000,
        generation_goals=((1, 6), (3, 5), (3, 10), (5, 2), (7, 4), (7, 6), (7, 9)),
    ),
}  # fmt: skip
"""D4RL's ``U_MAZE_TEST``, ``BIG_MAZE_TEST`` and ``HARDEST_MAZE_TEST`` (the maps of
``antmaze-{umaze,medium,large}-*-v2``; play and diverse datasets share their maze's map)."""


def get(name: str) -> Maze:
    """The maze called ``name``; an unknown name is refused with the known ones."""
    if name not in MAZES:
        raise ValueError(f"unknown maze {name!r}; the mazes are {', '.join(MAZES)}")
    return MAZES[name]


def maze_of(dataset: str) -> Maze:
    """The maze of an AntMaze dataset name: ``antmaze-medium-play`` -> ``MAZES["medium"]``."""
    for name, maze in MAZES.items():
        if f"antmaze-{name}" in dataset.lower().replace("_", "-"):
            return maze
    raise ValueError(f"{dataset!r} names no AntMaze maze ({', '.join(MAZES)})")


@functools.lru_cache(maxsize=256)
def distances_to(maze: Maze, target: Cell) -> np.ndarray:
    """Steps from every cell to ``target`` through free cells (4-neighbourhood), by breadth-first
    search from the target; ``inf`` for walls and cells that cannot reach it. Read-only and
    cached: a planner asks for the same few targets at every step."""
    if not maze.is_free(target):
        raise ValueError(f"{maze.name}: the target cell {target} is a wall")
    distance = np.full(maze.shape, np.inf)
    distance[target] = 0
    queue = deque([target])
    while queue:
        row, col = queue.popleft()
        for neighbour in ((row, col - 1), (row, col + 1), (row + 1, col), (row - 1, col)):
            if maze.is_free(neighbour) and distance[neighbour] == np.inf:
                distance[neighbour] = distance[row, col] + 1
                queue.append(neighbour)
    distance.setflags(write=False)
    return distance


def next_cell(maze: Maze, cell: Cell, target: Cell) -> Cell:
    """The neighbour of ``cell`` on a shortest path to ``target`` (``target`` once there)."""
    cell, target = tuple(cell), tuple(target)
    if cell == target:
        return target
    distance = distances_to(maze, target)
    if not maze.is_free(cell) or distance[cell] == np.inf:
        raise ValueError(f"{maze.name}: no path from {cell} to {target}")
    row, col = cell
    neighbours = [(row, col - 1), (row, col + 1), (row + 1, col), (row - 1, col)]
    return min((n for n in neighbours if maze.is_free(n)), key=lambda n: distance[n])


def waypoint(
    maze: Maze,
    xy,
    goal_xy,
    rng: np.random.Generator,
    noise: tuple[float, float] = (0.0, 0.25 * SCALING),
) -> np.ndarray:
    """Where the low-level policy heads next: the goal itself in the goal's cell, else the centre
    of the next cell on a shortest path plus uniform noise in ``[noise[0], noise[1])`` per axis,
    drawn afresh at every call (the data's controller uses :class:`WaypointPlanner`).

    D4RL's ``create_navigation_policy`` does the same with ``U(0, 1)`` noise (``add_random_noise``:
    ``U(0, scaling / 4)``), the default here; a point heading there never leaves free cells
    (tested), so neither the planner nor the noise walks the ant into a wall.
    """
    here, target = _free_cell(maze, xy), maze.xy_to_cell(goal_xy)
    step = next_cell(maze, here, target)
    if step == target:
        return np.asarray(goal_xy, np.float64)
    return maze.cell_to_xy(step) + rng.uniform(noise[0], noise[1], size=2)


ARRIVAL_RADIUS = 0.5
"""A :class:`WaypointPlanner` turns toward the next cell once within this distance of the middle of
the cell's noisy waypoints (its centre plus 0.5 per axis)."""


class WaypointPlanner:
    """:func:`waypoint` with one memory: the ant first heads for the cell it has entered (its
    centre plus the noise) and turns toward the next cell on the path only once within
    :data:`ARRIVAL_RADIUS` of the middle of those waypoints (the centre plus 0.5 per axis).

    Heading for the next cell as soon as a cell is entered cuts every corner: the ant turns at the
    cell's edge and passes a corner cell some 2 m from its middle. In medium that means it never
    comes near the evaluation goal, which lies in the corner cell (6, 6) that the way to the
    generation goal (6, 5) passes: medium-play had no reward at all. D4RL's truncating
    ``_xy_to_rowcol`` makes its ant reach each cell's centre before turning when it moves toward
    +x or +y, and Minari's controller moves on only within 0.45 of each waypoint; this does the
    same in every direction. One planner per episode (its goal is fixed).
    """

    def __init__(self, maze: Maze, goal_xy, noise: tuple[float, float] = (0.0, 0.25 * SCALING)):
        self.maze, self.noise = maze, noise
        self.goal = np.asarray(goal_xy, np.float64)
        self.goal_cell = maze.xy_to_cell(self.goal)
        self.cell: Cell | None = None
        self.centred = False

    def __call__(self, xy, rng: np.random.Generator) -> np.ndarray:
        maze = self.maze
        here = _free_cell(maze, xy)
        if here != self.cell:
            self.cell, self.centred = here, False
        middle = maze.cell_to_xy(here) + np.mean(self.noise)  # where the noisy waypoints centre
        self.centred |= bool(np.linalg.norm(xy - middle) <= ARRIVAL_RADIUS)
        aim = next_cell(maze, here, self.goal_cell) if self.centred else here
        if aim == self.goal_cell:
            return self.goal.copy()
        return maze.cell_to_xy(aim) + rng.uniform(self.noise[0], self.noise[1], size=2)


def d4rl_cell(maze: Maze, xy) -> Cell:
    """The cell D4RL's ``_xy_to_rowcol`` gives ``xy``: ``(int(1 + y / 4), int(1 + x / 4))`` with
    x, y raised to at least 1e-4. Every map starts at cell (1, 1), so a cell's index covers the
    square from its centre to the next centre toward +x, +y: half a cell off the cell ``xy`` is
    in (:meth:`Maze.xy_to_cell`), and sometimes a wall."""
    x, y = (max(float(v), 1e-4) for v in xy)
    return int(1 + y / SCALING), int(1 + x / SCALING)


def d4rl_waypoint(maze: Maze, xy, goal_xy, rng: np.random.Generator) -> np.ndarray:
    """D4RL's ``create_navigation_policy`` at one step, with no memory: the cells of the torso
    and the goal by :func:`d4rl_cell`; the goal itself once the next cell on a shortest path is
    the goal's, else that cell's centre plus ``U(0, 1)`` per axis, drawn afresh at every step.

    D4RL's breadth-first search may start from a wall cell (its truncated lookup puts the torso
    there near a wall) and steps from it to a free neighbour on a shortest path, as here (ties
    may break differently). A wall cell with no such neighbour, where D4RL's search would raise,
    falls back to the cell the torso is actually in."""
    here, target = d4rl_cell(maze, xy), d4rl_cell(maze, goal_xy)
    step = _d4rl_next_cell(maze, here, target)
    if step is None:
        step = next_cell(maze, _free_cell(maze, xy), target)
    if step == target:
        return np.asarray(goal_xy, np.float64)
    return maze.cell_to_xy(step) + rng.uniform(0.0, 0.25 * SCALING, size=2)


def _d4rl_next_cell(maze: Maze, here: Cell, target: Cell) -> Cell | None:
    """:func:`next_cell`, also from a wall cell (None where no free neighbour leads on)."""
    if here == target or maze.is_free(here):
        return next_cell(maze, here, target)
    distance = distances_to(maze, target)
    row, col = here
    neighbours = [(row, col - 1), (row, col + 1), (row + 1, col), (row - 1, col)]
    steps = [n for n in neighbours if maze.is_free(n) and distance[n] < np.inf]
    return min(steps, key=lambda n: distance[n]) if steps else None


def _free_cell(maze: Maze, xy) -> Cell:
    """The cell ``xy`` is in; the nearest free cell where a wall's edge pushed it into a wall's."""
    here = maze.xy_to_cell(xy)
    if maze.is_free(here):
        return here
    return min(maze.free_cells, key=lambda c: np.linalg.norm(maze.cell_to_xy(c) - xy))


def is_success(xy, goal_xy, tolerance: float = GOAL_TOLERANCE) -> np.ndarray:
    """Whether ``xy`` (``[..., 2]``) lies within ``tolerance`` of ``goal_xy`` (D4RL: 0.5, inclusive)."""
    return np.linalg.norm(np.asarray(xy) - np.asarray(goal_xy), axis=-1) <= tolerance


def relabel(next_xy, goal_xy, tolerance: float = GOAL_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """D4RL's sparse relabelling of AntMaze data: reward 1 where the *next* position is within
    ``tolerance`` of the evaluation goal, else 0; the same transitions are terminals.

    D4RL's ``relabel_antmaze_rewards.py`` reads the next position from the following row of the
    file, which at an episode's end is the next episode's first state; here it comes from each
    transition's own next observation.
    """
    success = is_success(next_xy, goal_xy, tolerance)
    return success.astype(np.float32), success


def training_rewards(rewards: np.ndarray) -> np.ndarray:
    """The sparse rewards as IQL and CORL train on them for AntMaze: ``r - 1`` (0 at the goal,
    -1 elsewhere)."""
    return np.asarray(rewards, np.float32) - 1.0


def success_score(successes) -> float:
    """D4RL's normalised AntMaze score: 100 x the fraction of successful episodes (its reference
    scores are 0 and 1, and an episode's return is 1 on success, 0 otherwise)."""
    successes = np.asarray(successes, np.float64).reshape(-1)
    if successes.size == 0:
        raise ValueError("no episodes to score")
    return 100.0 * float(successes.mean())
