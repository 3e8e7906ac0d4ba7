"""The LOMPR's processing paths (docs/interface.md, paths), sampled every 40 ms.

Three paths are in use on the mirror (a disk of radius 0.200 m at z = 1.097 m):

- `spiral`: the seed paper's Eq. 29, x = a t_h cos(pi/2 t_h + pi/2), y = a t_h sin(...),
  t_h in [0, 10] over one 40 s pass;
- `grid`: a raster of parallel lines clipped to the disk, run back and forth;
- `concentric`: circles at evenly spaced radii up to the disk's, joined by radial moves.

Processing is continuous: each pass is followed by a smooth return to the start of the next
pass (a cubic Hermite segment matching position and velocity at both ends, held inside the
disk), so one pass plus its return is a `PathCycle` that repeats exactly, unless the feed
varies (`feed_variation`): then each pass runs the same geometry at a feed that speeds up
and slows down along it, drawn anew for each pass (as a feed override and a CAM program's
feed changes do), so that what the tool does next is not a function of where it is. Every
sample is a tool-tip position in the robot frame `lompr_base` (Z down) [m] with the tool axis
vertical. Corners of the grid and concentric paths are rounded by a moving average over
`corner_time`, and those passes start and end at rest (speed ramps over `ramp_time`), so
commanded accelerations stay finite.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Sample period of the paths and of everything recorded [s] (25 Hz; docs/interface.md).
SAMPLE_PERIOD = 0.04
PATH_KINDS: tuple[str, ...] = ('spiral', 'grid', 'concentric')


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
    feed_speed: float  # tool speed along the grid and concentric paths [m/s]
    ramp_time: float  # grid/concentric passes start and end at rest: time to reach feed [s]
    corner_time: float  # moving-average window rounding grid/concentric corners [s]
    #: largest relative change of the feed along a pass, drawn anew for each pass, in [0, 1)
    #: (0: every pass the same)
    feed_variation: float = 0.0


#: Shortest period of the feed's variation along a pass [s] (`PathCycle.pass_positions`).
FEED_VARIATION_PERIOD = 4.0


@dataclass(frozen=True)
class PathCycle:
    """One pass followed by its return: the unit that repeats, pass after pass (with
    `feed_variation`, the same geometry at another feed each pass, seeded by `seed`)."""

    kind: str
    positions: np.ndarray  # (M, 3) tool-tip positions [m], one per sample period
    pass_samples: int  # rows [0, pass_samples) are the pass, the rest is the return
    sample_period: float  # [s]
    feed_variation: float = 0.0
    seed: int = 0
    #: The last passes' positions (`pass_positions`), by pass number: a twin asks for each
    #: sample, and for the plan after it, many times per pass.
    _passes: dict[int, np.ndarray] = field(default_factory=dict, init=False, repr=False,
                                           compare=False)

    def __len__(self) -> int:
        return len(self.positions)

    def sample(self, start: int, count: int) -> np.ndarray:
        """(count, 3) positions of samples start .. start+count-1 of the endless path."""
        index = np.arange(start, start + count)
        if not self.feed_variation:
            return self.positions[index % len(self.positions)]
        passes = index // len(self.positions)
        out = np.empty((count, 3))
        for number in np.unique(passes):
            rows = passes == number
            out[rows] = self.pass_positions(int(number))[index[rows] % len(self.positions)]
        return out

    def pass_positions(self, number: int) -> np.ndarray:
        """(M, 3) positions of pass `number` and its return: the pass's geometry run at
        the feed x g(s), s in [0, 1] along the pass's time, g = 1 + sum_j a_j sin(2 pi j s)
        with random a_j (sum |a_j| = feed_variation, periods down to
        `FEED_VARIATION_PERIOD`): the pass keeps its duration, its ends their speed (so the
        return joins smoothly), and the samples are the pass's cubic spline at the warped
        times."""
        cached = self._passes.get(number)
        if cached is not None:
            return cached
        from scipy.interpolate import CubicSpline  # the twin only: not on the nodes' path

        count = self.pass_samples
        duration = (count - 1) * self.sample_period
        harmonics = np.arange(1, max(1, int(duration / FEED_VARIATION_PERIOD)) + 1)
        weights = np.random.default_rng([self.seed, number]).normal(size=len(harmonics))
        weights *= self.feed_variation / np.abs(weights).sum()
        s = np.linspace(0.0, 1.0, count)[:, None]
        warped = s[:, 0] + ((1.0 - np.cos(2 * np.pi * harmonics * s)) / (2 * np.pi * harmonics)
                            ) @ weights
        spline = CubicSpline(np.linspace(0.0, 1.0, count), self.positions[:count])
        positions = self.positions.copy()
        positions[:count] = spline(warped)
        positions.flags.writeable = False  # shared by every caller of the cache
        if len(self._passes) >= 2:  # this pass and the one before (a plan crosses a join)
            self._passes.pop(min(self._passes))
        self._passes[number] = positions
        return positions

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


def constant_speed(waypoints: np.ndarray, config: PathConfig,
                   sample_period: float = SAMPLE_PERIOD) -> np.ndarray:
    """(N, 2) a polyline run at `feed_speed` from rest to rest (`speed_profile`), corners
    rounded by a centred moving average over `corner_time` (the ends held, so the path
    starts and ends where the polyline does)."""
    steps = np.linalg.norm(np.diff(waypoints, axis=0), axis=1)
    keep = np.concatenate([[True], steps > 0.0])
    waypoints = waypoints[keep]
    arc = np.concatenate([[0.0], np.cumsum(steps[steps > 0.0])])
    s = speed_profile(arc[-1], config.feed_speed, config.ramp_time, sample_period)
    path = np.stack([np.interp(s, arc, waypoints[:, i]) for i in range(2)], -1)
    half = round(0.5 * config.corner_time / sample_period)
    if half == 0:
        return path
    padded = np.vstack([np.repeat(path[:1], half, 0), path, np.repeat(path[-1:], half, 0)])
    kernel = np.full(2 * half + 1, 1.0 / (2 * half + 1))
    return np.stack([np.convolve(padded[:, i], kernel, mode='valid') for i in range(2)], -1)


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


def build_cycle(kind: str, config: PathConfig, sample_period: float = SAMPLE_PERIOD,
                seed: int = 0) -> PathCycle:
    """One pass of `kind` and the smooth return to its own start (velocities by differences
    at both ends), at height `config.height`; with `config.feed_variation`, each pass's feed
    drawn from `seed` and the pass number."""
    xy = pass_xy(kind, config, sample_period)
    velocity_end = (xy[-1] - xy[-2]) / sample_period
    velocity_start = (xy[1] - xy[0]) / sample_period
    back = hermite_transition(xy[-1], velocity_end, xy[0], velocity_start,
                              config.return_duration, sample_period)
    # A return that leaves the rim tangentially bulges out by up to ~1 mm: pull it back
    # radially onto the disk (the velocity stays continuous to a few mm/s).
    radius = np.linalg.norm(back, axis=1, keepdims=True)
    back *= np.minimum(1.0, config.radius / np.maximum(radius, 1e-300))
    cycle = np.vstack([xy, back])
    positions = np.column_stack([cycle, np.full(len(cycle), config.height)])
    if not 0.0 <= config.feed_variation < 1.0:
        msg = f'feed_variation must lie in [0, 1), got {config.feed_variation}'
        raise ValueError(msg)
    return PathCycle(kind=kind, positions=positions, pass_samples=len(xy),
                     sample_period=sample_period, feed_variation=config.feed_variation,
                     seed=seed)
