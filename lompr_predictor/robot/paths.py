# SPDX-License-Identifier: Apache-2.0
"""The LOMPR's processing paths (docs/interface.md, paths), sampled every 40 ms.

Six programs run on the mirror (a disk of radius 0.200 m at z = 1.097 m):

- `spiral`: the seed paper's Eq. 29, x = a t_h cos(pi/2 t_h + pi/2), y = a t_h sin(...),
  t_h in [0, 10] over one 40 s pass;
- `grid`: a raster of parallel lines clipped to the disk, run back and forth;
- `concentric`: circles at evenly spaced radii up to the disk's, joined by radial moves;
- `lissajous`: a Lissajous curve of the square mapped onto the disk (X and Y sines of
  different frequencies), covering it densely;
- `radial`: a star: strokes through the centre at directions evenly spread over a half
  turn, one after the other across a short arc of the rim (a U-turn in each direction);
- `random`: random waypoints over the disk joined at a feed that changes along the pass,
  corners rounded: a different path every pass, drawn from the seed and the pass number.

Processing is continuous: each pass is followed by a return to the start of the next pass,
so one pass plus its return is a `PathCycle` of a fixed number of samples. For spiral, grid
and concentric the return is a cubic Hermite segment matching position and velocity at
both ends, held inside the disk. Lissajous, radial and random passes run from rest to rest
(the Lissajous curve less its last `return_duration`), their returns are straight moves
from rest to rest, and the corners of the whole cycle are rounded twice by a moving
average over `corner_time`, taken across the joins (so their acceleration is continuous and
their jerk bounded). Every cycle but random's repeats exactly. The feed may vary
(`feed_variation`): then each pass runs its geometry at a feed that speeds up and slows down
along it, drawn anew for each pass (as a feed override and a CAM program's feed changes
do), so that what the tool does next is not a function of where it is. Every sample is a
tool-tip position in the robot frame `lompr_base` (Z down) [m] with the tool axis
vertical. Corners of the grid and
concentric paths are rounded once by that moving average, and those passes start and end
at rest (speed ramps over `ramp_time`), so commanded accelerations stay finite.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np

#: Sample period of the paths and of everything recorded [s] (25 Hz; docs/interface.md).
SAMPLE_PERIOD = 0.04
PATH_KINDS: tuple[str, ...] = ('spiral', 'grid', 'concentric', 'lissajous', 'radial', 'random')


@dataclass(frozen=True)
class PathConfig:
    """Path parameters (SI units); the defaults are in `config/twin.yaml`, section `path`."""

    height: float  # z of the mirror surface the tool works on [m]
    radius: float  # radius of the mirror disk every path stays within [m]
    spiral_pitch: float  # a in Eq. 29: radius grows by a per unit t_h [m]
    spiral_turn_rate: float  # angle per unit t_h in Eq. 29 [rad]
    spiral_duration: float  # one pass, t_h from 0 to radius / a [s]
    return_duration: float  # smooth move from a pass's end to the next pass's start [s]
    grid_spacing: float  # distance between raster lines [m]
    concentric_circles: int  # circles at radius * k / n, k = 1..n
    feed_speed: float  # tool speed of grid, concentric, radial; random's mean feed [m/s]
    ramp_time: float  # passes that start and end at rest: time to reach their speed [s]
    corner_time: float  # moving-average window that rounds corners [s]
    lissajous_duration: float  # one closed Lissajous curve, its pass and its return [s]
    lissajous_x_cycles: int  # periods of the X sine along the curve
    lissajous_y_cycles: int  # periods of the Y sine along the curve
    radial_strokes: int  # strokes through the centre per radial pass (odd: ends near start)
    random_duration: float  # one random pass [s]
    random_feed_variation: float  # largest relative change of the random pass's feed [-]
    #: largest relative change of the feed along a pass, drawn anew for each pass, in [0, 1)
    #: (0: every pass the same)
    feed_variation: float = 0.0


#: Shortest period of the feed's variation along a pass [s] (`PathCycle.pass_positions`).
FEED_VARIATION_PERIOD = 4.0


@dataclass(frozen=True)
class PathCycle:
    """One pass followed by its return: the unit that repeats, pass after pass (with
    `feed_variation`, the same geometry at another feed each pass, seeded by `seed`; with a
    `program`, another geometry each pass)."""

    kind: str
    positions: np.ndarray  # (M, 3) tool-tip positions [m], one per sample period (pass 0)
    pass_samples: int  # rows [0, pass_samples) are the pass, the rest is the return
    sample_period: float  # [s]
    feed_variation: float = 0.0
    seed: int = 0
    #: (M, 3) positions of pass `number` and its return, for a program whose geometry
    #: changes from pass to pass (`random`); None: every pass runs `positions`.
    program: Callable[[int], np.ndarray] | None = field(default=None, repr=False,
                                                       compare=False)
    #: The last passes' positions (`pass_positions`), by pass number: a twin asks for each
    #: sample, and for the plan after it, many times per pass.
    _passes: dict[int, np.ndarray] = field(default_factory=dict, init=False, repr=False,
                                           compare=False)

    def __len__(self) -> int:
        return len(self.positions)

    def sample(self, start: int, count: int) -> np.ndarray:
        """(count, 3) positions of samples start .. start+count-1 of the endless path."""
        index = np.arange(start, start + count)
        if not self.feed_variation and self.program is None:
            return self.positions[index % len(self.positions)]
        passes = index // len(self.positions)
        out = np.empty((count, 3))
        for number in np.unique(passes):
            rows = passes == number
            out[rows] = self.pass_positions(int(number))[index[rows] % len(self.positions)]
        return out

    def pass_positions(self, number: int) -> np.ndarray:
        """(M, 3) positions of pass `number` and its return: the pass's geometry (the
        program's for this pass, if any) run at the feed x g(s), s in [0, 1] along the
        pass's time, g = 1 + sum_j a_j sin(2 pi j s) with random a_j (sum |a_j| =
        feed_variation, periods down to `FEED_VARIATION_PERIOD`): the pass keeps its
        duration, its ends their speed (so the return joins smoothly), and the samples are
        the pass's cubic spline at the warped times."""
        cached = self._passes.get(number)
        if cached is not None:
            return cached
        positions = (self.positions if self.program is None else self.program(number)).copy()
        if self.feed_variation:
            positions[:self.pass_samples] = self._varied_feed(positions[:self.pass_samples],
                                                              number)
        positions.flags.writeable = False  # shared by every caller of the cache
        if len(self._passes) >= 2:  # this pass and the one before (a plan crosses a join)
            self._passes.pop(min(self._passes))
        self._passes[number] = positions
        return positions

    def _varied_feed(self, geometry: np.ndarray, number: int) -> np.ndarray:
        """The pass `geometry` (pass_samples, 3) at pass `number`'s feed (`pass_positions`)."""
        from scipy.interpolate import CubicSpline  # the twin only: not on the nodes' path

        count = self.pass_samples
        duration = (count - 1) * self.sample_period
        harmonics = np.arange(1, max(1, int(duration / FEED_VARIATION_PERIOD)) + 1)
        weights = np.random.default_rng([self.seed, number]).normal(size=len(harmonics))
        weights *= self.feed_variation / np.abs(weights).sum()
        s = np.linspace(0.0, 1.0, count)[:, None]
        warped = s[:, 0] + ((1.0 - np.cos(2 * np.pi * harmonics * s)) / (2 * np.pi * harmonics)
                            ) @ weights
        return CubicSpline(np.linspace(0.0, 1.0, count), geometry)(warped)

    def pass_index(self, start: int, count: int) -> np.ndarray:
        """(count,) pass number of each sample (a return belongs to the pass before it)."""
        return np.arange(start, start + count) // len(self.positions)

    def in_pass(self, start: int, count: int) -> np.ndarray:
        """(count,) True where a sample is on a pass, False on a return."""
        return np.arange(start, start + count) % len(self.positions) < self.pass_samples


def spiral_pass(config: PathConfig, sample_period: float = SAMPLE_PERIOD) -> np.ndarray:
    """(N, 2) Eq. 29 from t_h = 0 to radius / pitch inclusive."""
    t_end = config.radius / config.spiral_pitch
    count = round(config.spiral_duration / sample_period)
    t_h = np.linspace(0.0, t_end, count + 1)
    phase = config.spiral_turn_rate * t_h + 0.5 * np.pi
    return config.spiral_pitch * t_h[:, None] * np.stack([np.cos(phase), np.sin(phase)], -1)


def grid_waypoints(config: PathConfig) -> np.ndarray:
    """(K, 2) corners of a back-and-forth raster clipped to the disk."""
    lines = int(np.floor(2.0 * config.radius / config.grid_spacing))
    offsets = (np.arange(lines) - 0.5 * (lines - 1)) * config.grid_spacing
    points = []
    for j, y in enumerate(offsets):
        half = np.sqrt(max(config.radius ** 2 - y ** 2, 0.0))
        xs = (-half, half) if j % 2 == 0 else (half, -half)
        points += [(xs[0], y), (xs[1], y)]
    return np.array(points)


def concentric_waypoints(config: PathConfig, points_per_metre: float = 2000.0) -> np.ndarray:
    """(K, 2) a dense polyline: from the centre out along +X to each circle, once around it."""
    points = [np.zeros((1, 2))]
    for k in range(1, config.concentric_circles + 1):
        radius = config.radius * k / config.concentric_circles
        count = max(int(2.0 * np.pi * radius * points_per_metre), 16)
        angle = np.linspace(0.0, 2.0 * np.pi, count + 1)
        points.append(radius * np.stack([np.cos(angle), np.sin(angle)], -1))
    return np.vstack(points)


def speed_profile(length: float, speed: float, ramp_time: float,
                  sample_period: float = SAMPLE_PERIOD) -> np.ndarray:
    """Arc length [m] at each sample of a run over `length` that starts and ends at rest:
    the speed rises to `speed` over `ramp_time` (smoothstep, so the acceleration is
    continuous), cruises, and falls back to zero symmetrically."""
    ramp = min(ramp_time, length / speed)  # a short run never reaches full speed
    duration = length / speed + ramp
    t = np.arange(int(np.ceil(duration / sample_period)) + 1) * sample_period
    t = np.minimum(t, duration)

    def ramped(time: np.ndarray) -> np.ndarray:  # distance covered while speeding up
        x = np.clip(time / ramp, 0.0, 1.0)
        return speed * ramp * (x ** 3 - 0.5 * x ** 4)

    arc = ramped(t) + speed * np.clip(t - ramp, 0.0, None) - ramped(t - (duration - ramp))
    return arc * (length / arc[-1])


@dataclass(frozen=True)
class Polyline:
    """The polyline through some waypoints, repeated points skipped."""

    points: np.ndarray  # (K, 2) [m]
    lengths: np.ndarray  # (K,) arc length at each point [m], from 0

    @classmethod
    def through(cls, waypoints: np.ndarray) -> Polyline:
        steps = np.linalg.norm(np.diff(waypoints, axis=0), axis=1)
        keep = np.concatenate([[True], steps > 0.0])
        return cls(waypoints[keep], np.concatenate([[0.0], np.cumsum(steps[steps > 0.0])]))

    @property
    def length(self) -> float:
        return float(self.lengths[-1])

    def at(self, arc: np.ndarray) -> np.ndarray:
        """(N, 2) the points at arc lengths `arc` [m], within [0, length]."""
        return np.stack([np.interp(arc, self.lengths, self.points[:, i]) for i in range(2)], -1)


def moving_average(padded: np.ndarray, half: int, times: int = 1) -> np.ndarray:
    """(N - 2 times half, 2) the centred moving average over 2 half + 1 samples of `padded`
    (N, 2), applied `times` over (twice: a triangular window, the acceleration continuous)."""
    kernel = np.full(2 * half + 1, 1.0 / (2 * half + 1))
    for _ in range(times):
        padded = np.stack([np.convolve(padded[:, i], kernel, mode='valid') for i in range(2)],
                          -1)
    return padded


def corner_samples(config: PathConfig, sample_period: float) -> int:
    """Half the moving-average window that rounds corners, in samples (`corner_time`)."""
    return round(0.5 * config.corner_time / sample_period)


def polyline_run(waypoints: np.ndarray, config: PathConfig,
                 sample_period: float = SAMPLE_PERIOD) -> np.ndarray:
    """(N, 2) the polyline through `waypoints` run at `feed_speed` from rest to rest
    (`speed_profile`), its corners sharp."""
    polyline = Polyline.through(waypoints)
    return polyline.at(speed_profile(polyline.length, config.feed_speed, config.ramp_time,
                                     sample_period))


def constant_speed(waypoints: np.ndarray, config: PathConfig,
                   sample_period: float = SAMPLE_PERIOD) -> np.ndarray:
    """(N, 2) a polyline run at `feed_speed` from rest to rest (`polyline_run`), corners
    rounded by a centred moving average over `corner_time` (the ends held, so the path
    starts and ends where the polyline does)."""
    path = polyline_run(waypoints, config, sample_period)
    half = corner_samples(config, sample_period)
    if half == 0:
        return path
    padded = np.vstack([np.repeat(path[:1], half, 0), path, np.repeat(path[-1:], half, 0)])
    return moving_average(padded, half)


def with_return(pass_xy: np.ndarray, start: np.ndarray, config: PathConfig,
                sample_period: float = SAMPLE_PERIOD) -> np.ndarray:
    """(M, 2) a pass that ends at rest, then the return from rest to rest (a cubic over
    `return_duration`, a straight move) to `start`, the next pass's first point."""
    rest = np.zeros(2)
    back = hermite_transition(pass_xy[-1], rest, start, rest, config.return_duration,
                              sample_period)
    return np.vstack([pass_xy, back])


def rounded_cycle(raw: np.ndarray, half: int, before: np.ndarray | None = None,
                  after: np.ndarray | None = None) -> np.ndarray:
    """(M, 2) the cycle `raw` (M, 2) with its corners rounded twice by the moving average
    over 2 half + 1 samples, taken across its ends: over the 2 half samples `before` and
    `after` it (the neighbouring cycles'), or round the cycle itself when it repeats."""
    pad = 2 * half
    if before is None or after is None:
        padded = raw[np.arange(-pad, len(raw) + pad) % len(raw)]
    else:
        padded = np.vstack([before, raw, after])
    return moving_average(padded, half, times=2)


#: Phase of the Lissajous curve's X sine [rad] (`lissajous_curve`).
LISSAJOUS_PHASE = 0.5 * np.pi


def lissajous_curve(config: PathConfig, theta: np.ndarray) -> np.ndarray:
    """(N, 2) the closed curve x = sin(a theta + pi/2), y = sin(b theta) of the square
    [-1, 1]^2 (a, b: `lissajous_x_cycles`, `lissajous_y_cycles`; theta [rad]) mapped onto
    the disk by (x sqrt(1 - y^2/2), y sqrt(1 - x^2/2)) (whose squared radius x^2 + y^2 -
    x^2 y^2 is at most 1: the square's edge on the rim), times `radius`."""
    x = np.sin(config.lissajous_x_cycles * theta + LISSAJOUS_PHASE)
    y = np.sin(config.lissajous_y_cycles * theta)
    return config.radius * np.stack([x * np.sqrt(1.0 - 0.5 * y ** 2),
                                     y * np.sqrt(1.0 - 0.5 * x ** 2)], -1)


def lissajous_pass(config: PathConfig, sample_period: float = SAMPLE_PERIOD) -> np.ndarray:
    """(N, 2) the Lissajous curve from rest to rest (theta at 2 pi / `lissajous_duration`,
    ramped over `ramp_time`), all but its last `return_duration`, which the return cuts
    short."""
    rate = 2.0 * np.pi / config.lissajous_duration
    end = rate * (config.lissajous_duration - config.return_duration)
    if end <= 0.0:
        msg = (f'lissajous_duration ({config.lissajous_duration:g} s) must be longer than '
               f'return_duration ({config.return_duration:g} s)')
        raise ValueError(msg)
    return lissajous_curve(config, speed_profile(end, rate, config.ramp_time, sample_period))


def radial_waypoints(config: PathConfig, points_per_metre: float = 2000.0) -> np.ndarray:
    """(K, 2) a star: stroke k through the centre from the rim at angle k (pi + d) to the
    opposite rim, then along the rim by d = pi / `radial_strokes` to the next stroke's
    start. The strokes cross the disk in every direction k d, k = 0 .. strokes - 1; with an
    odd number of strokes the last ends an arc d short of the first's start."""
    step = np.pi / config.radial_strokes
    arc = np.linspace(0.0, step, max(int(config.radius * step * points_per_metre), 2) + 1)
    points = []
    for k in range(config.radial_strokes):
        start = k * (np.pi + step)
        rim = start + np.pi + (arc if k < config.radial_strokes - 1 else arc[:1])
        angle = np.concatenate([[start], rim])
        points.append(config.radius * np.stack([np.cos(angle), np.sin(angle)], -1))
    return np.vstack(points)


def repeating_cycle(kind: str, config: PathConfig,
                    sample_period: float = SAMPLE_PERIOD) -> tuple[np.ndarray, int]:
    """(M, 2) a `lissajous` or `radial` pass from rest to rest and its return to its own
    start, rounded round the cycle (`rounded_cycle`), and the pass's sample count."""
    if kind == 'lissajous':
        xy = lissajous_pass(config, sample_period)
    else:
        xy = polyline_run(radial_waypoints(config), config, sample_period)
    raw = with_return(xy, xy[0], config, sample_period)
    return rounded_cycle(raw, corner_samples(config, sample_period)), len(xy)


#: Random pass waypoints are drawn this many at a time (`random_waypoints`).
WAYPOINT_BATCH = 16
#: Third word of the seed of a random pass's waypoints and of its feed: streams apart from
#: each other and from `feed_variation`'s (seeded by the run's seed and the pass number).
RANDOM_WAYPOINT_STREAM, RANDOM_FEED_STREAM = 1, 2


def random_waypoints(config: PathConfig, seed: int, number: int, length: float) -> np.ndarray:
    """(K, 2) points drawn uniformly over the disk for pass `number` of the run `seed`,
    until the polyline through them is at least `length` [m] long; the first is the pass's
    start."""
    rng = np.random.default_rng([seed, number, RANDOM_WAYPOINT_STREAM])
    points = np.empty((0, 2))
    while len(points) < 2 or Polyline.through(points).length < length:
        u = rng.random((WAYPOINT_BATCH, 2))
        angle = 2.0 * np.pi * u[:, 1]
        batch = config.radius * np.sqrt(u[:, :1]) * np.stack([np.cos(angle), np.sin(angle)], -1)
        points = np.vstack([points, batch])
    return points


def random_feed_arc(config: PathConfig, rng: np.random.Generator,
                    sample_period: float = SAMPLE_PERIOD) -> np.ndarray:
    """Arc length [m] at each sample of a random pass (`random_duration`, both ends
    included), run at `feed_speed` x g(t) x e(t): g = 1 + sum_j a_j sin(2 pi j t / T +
    phi_j), random a_j (sum |a_j| = `random_feed_variation`, periods down to
    `FEED_VARIATION_PERIOD`) and phases; e rises from 0 to 1 over `ramp_time` (smoothstep)
    and falls back at the end, so the pass runs from rest to rest."""
    count = round(config.random_duration / sample_period)
    duration = count * sample_period
    t = np.arange(count + 1) * sample_period
    harmonics = np.arange(1, max(1, int(duration / FEED_VARIATION_PERIOD)) + 1)
    weights = rng.normal(size=len(harmonics))
    weights *= config.random_feed_variation / np.abs(weights).sum()
    phases = rng.uniform(0.0, 2.0 * np.pi, len(harmonics))
    g = 1.0 + np.sin(2.0 * np.pi * np.outer(t / duration, harmonics) + phases) @ weights
    x = np.clip(np.minimum(t, duration - t) / config.ramp_time, 0.0, 1.0)
    speed = config.feed_speed * g * x ** 2 * (3.0 - 2.0 * x)
    return np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * sample_period)])


def random_raw(config: PathConfig, sample_period: float, seed: int, number: int) -> np.ndarray:
    """(M, 2) random pass `number` and its return to the next pass's start, corners sharp:
    the waypoints' polyline at the pass's feed (`random_feed_arc`), then `with_return`."""
    arc = random_feed_arc(config, np.random.default_rng([seed, number, RANDOM_FEED_STREAM]),
                          sample_period)
    xy = Polyline.through(random_waypoints(config, seed, number, arc[-1])).at(arc)
    start = random_waypoints(config, seed, number + 1, 0.0)[0]
    return with_return(xy, start, config, sample_period)


def random_cycle(config: PathConfig, sample_period: float, seed: int, number: int) -> np.ndarray:
    """(M, 3) random pass `number` and its return (`random_raw`), rounded across the passes
    before and after it (at rest before the first), so that the passes join as smoothly as
    any two samples."""
    half = corner_samples(config, sample_period)
    raw = random_raw(config, sample_period, seed, number)
    before = (np.repeat(raw[:1], 2 * half, 0) if number == 0 else
              random_raw(config, sample_period, seed, number - 1)[len(raw) - 2 * half:])
    after = random_raw(config, sample_period, seed, number + 1)[:2 * half]
    xy = rounded_cycle(raw, half, before, after)
    return np.column_stack([xy, np.full(len(xy), config.height)])


def hermite_transition(start: np.ndarray, start_velocity: np.ndarray, end: np.ndarray,
                       end_velocity: np.ndarray, duration: float,
                       sample_period: float = SAMPLE_PERIOD) -> np.ndarray:
    """Interior samples of the cubic from (start, start_velocity) to (end, end_velocity):
    position and velocity continuous at both joins."""
    count = round(duration / sample_period)
    s = (np.arange(1, count) / count)[:, None]
    h00, h10 = 2 * s ** 3 - 3 * s ** 2 + 1, s ** 3 - 2 * s ** 2 + s
    h01, h11 = -2 * s ** 3 + 3 * s ** 2, s ** 3 - s ** 2
    return (h00 * start + h10 * duration * start_velocity
            + h01 * end + h11 * duration * end_velocity)


def pass_xy(kind: str, config: PathConfig, sample_period: float = SAMPLE_PERIOD) -> np.ndarray:
    """(N, 2) X/Y of one pass of `kind`."""
    if kind == 'spiral':
        return spiral_pass(config, sample_period)
    if kind == 'grid':
        waypoints = grid_waypoints(config)
    elif kind == 'concentric':
        waypoints = concentric_waypoints(config)
    else:
        msg = f'unknown path {kind!r}; choose one of {", ".join(PATH_KINDS)}'
        raise ValueError(msg)
    return constant_speed(waypoints, config, sample_period)


def open_cycle(kind: str, config: PathConfig,
               sample_period: float = SAMPLE_PERIOD) -> tuple[np.ndarray, int]:
    """(M, 2) one pass of `kind` (spiral, grid, concentric) and the smooth return to its own
    start (velocities by differences at both ends), and the pass's sample count."""
    xy = pass_xy(kind, config, sample_period)
    velocity_end = (xy[-1] - xy[-2]) / sample_period
    velocity_start = (xy[1] - xy[0]) / sample_period
    back = hermite_transition(xy[-1], velocity_end, xy[0], velocity_start,
                              config.return_duration, sample_period)
    # A return that leaves the rim tangentially bulges out by up to ~1 mm: pull it back
    # radially onto the disk (the velocity stays continuous to a few mm/s).
    radius = np.linalg.norm(back, axis=1, keepdims=True)
    back *= np.minimum(1.0, config.radius / np.maximum(radius, 1e-300))
    return np.vstack([xy, back]), len(xy)


def build_cycle(kind: str, config: PathConfig, sample_period: float = SAMPLE_PERIOD,
                seed: int = 0) -> PathCycle:
    """One pass of `kind` and its return to the next pass's start (module docstring), at
    height `config.height`; with `config.feed_variation`, each pass's feed drawn from `seed`
    and the pass number, and for `random` each pass's path."""
    if not 0.0 <= config.feed_variation < 1.0:
        msg = f'feed_variation must lie in [0, 1), got {config.feed_variation}'
        raise ValueError(msg)
    program = None
    if kind == 'random':
        program = partial(random_cycle, config, sample_period, seed)
        positions = program(0)
        pass_samples = round(config.random_duration / sample_period) + 1
    else:
        xy, pass_samples = (repeating_cycle if kind in ('lissajous', 'radial') else
                            open_cycle)(kind, config, sample_period)
        positions = np.column_stack([xy, np.full(len(xy), config.height)])
    return PathCycle(kind=kind, positions=positions, pass_samples=pass_samples,
                     sample_period=sample_period, feed_variation=config.feed_variation,
                     seed=seed, program=program)
