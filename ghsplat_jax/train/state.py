"""The training state: surfels padded to a fixed capacity with an `active` mask, optimiser
state and densification statistics, so shapes never change under jit."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ghsplat_jax.core.precision import FLOAT32
from ghsplat_jax.core.surfels import Surfels
from ghsplat_jax.raster.render import capacity_bucket
from ghsplat_jax.train.exposure import ExposureState
from ghsplat_jax.train.pose import PoseState

INACTIVE_LOGIT = -20.0  # sigmoid ~ 2e-9: an empty slot is invisible even if it were drawn


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TrainState:
    params: Surfels        # (cap, ...) raw parameters; rows where active is False are free slots
    active: jax.Array      # (cap,) bool
    opt_state: dict        # per-group optax Adam state (rows aligned with params)
    grad_accum: jax.Array  # (cap,) summed NDC norm of the projected-centre gradient
    grad_count: jax.Array  # (cap,) number of views in which the surfel was visible
    max_radii: jax.Array   # (cap,) largest screen radius (px) since the last densification
    step: jax.Array        # () int32: steps completed
    pose: PoseState | None = None  # per-view pose corrections (TrainConfig.pose_refine), else None
    exposure: ExposureState | None = None  # per-view colour corrections (TrainConfig.exposure_compensation)

    @property
    def capacity(self) -> int:
        return self.active.shape[0]

    def num_active(self) -> int:
        return int(jnp.sum(self.active))

    def active_surfels(self) -> Surfels:
        """The live surfels as a compact host Surfels (for saving and evaluation)."""
        mask = np.asarray(self.active)
        return self.params.to_numpy().take(mask)


def empty_params(capacity: int, sh_degree: int) -> Surfels:
    k = (sh_degree + 1) ** 2 - 1
    return Surfels(
        means=np.zeros((capacity, 3), np.float32),
        quats=np.tile(np.array([1, 0, 0, 0], np.float32), (capacity, 1)),
        log_scales=np.full((capacity, 2), np.log(1e-3), np.float32),
        opacity_logits=np.full((capacity,), INACTIVE_LOGIT, np.float32),
        sh_dc=np.zeros((capacity, 3), np.float32),
        sh_rest=np.zeros((capacity, k, 3), np.float32),
    )


def knn_log_scales(points: np.ndarray, k: int = 3) -> np.ndarray:
    """log of the root mean squared distance to the k nearest neighbours (3DGS/2DGS init)."""
    from scipy.spatial import cKDTree

    n = len(points)
    if n < 2:
        return np.full((n,), np.log(0.01), np.float32)
    kk = min(k, n - 1)
    dist, _ = cKDTree(points).query(points, k=kk + 1)
    d2 = np.mean(np.asarray(dist).reshape(n, -1)[:, 1:] ** 2, axis=1)
    return (0.5 * np.log(np.maximum(d2, 1e-7))).astype(np.float32)


def random_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4)).astype(np.float32)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_init_box(cameras, fallback_center, fallback_half: float) -> tuple[np.ndarray, float]:
    """Centre and half-size of the cube that random initial points fill: where the cameras look.

    The centre is the point closest (least squares) to every optical axis; the half-size is what
    the widest half field of view spans at the median camera distance to it (NeRF-synthetic
    lego: about the 1.3 of the 3DGS box). Cameras that look one way (a forward-facing capture),
    or whose axes meet behind them, have no such point: then the fallback cube."""
    origins, axes, half_fov = [], [], []
    for cam in cameras:
        w2c = np.asarray(cam.world_to_cam, np.float64)
        K = np.asarray(cam.K, np.float64)
        origins.append(-w2c[:3, :3].T @ w2c[:3, 3])
        axes.append(w2c[2, :3] / np.linalg.norm(w2c[2, :3]))  # the camera's +z in the world
        half_fov.append(np.arctan(max(cam.width / (2 * K[0, 0]), cam.height / (2 * K[1, 1]))))
    fallback = np.asarray(fallback_center, np.float64), float(fallback_half)
    if len(origins) < 2:
        return fallback
    o, d = np.array(origins), np.array(axes)
    across = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # projections across each axis
    A, b = across.sum(0), np.einsum("nij,nj->i", across, o)
    if np.linalg.eigvalsh(A / len(o))[0] < 0.05:  # axes within ~13 degrees of one direction
        return fallback
    center = np.linalg.solve(A, b)
    if np.median(np.einsum("ni,ni->n", center - o, d)) <= 0:
        return fallback
    return center, float(np.median(np.linalg.norm(o - center, axis=1)) * np.tan(max(half_fov)))


def needs_random_init(num_points: int, config) -> bool:
    """Too few (finite) dataset points to start from: training starts at random points instead."""
    return num_points < config.init_min_points


def initial_surfels(points, colors, box_center, box_half: float, extent: float, config, rng) -> Surfels:
    """Host Surfels from dataset points, or random points in the cube box_center +- box_half
    when there are too few (see `random_init_box`); `extent` scales `init_scale_max`."""
    from ghsplat_jax.core.sh import rgb_to_dc

    points = np.zeros((0, 3), np.float32) if points is None else np.asarray(points, np.float32).reshape(-1, 3)
    finite = np.all(np.isfinite(points), axis=1)
    points = points[finite]
    colors = None if colors is None else np.asarray(colors, np.float32).reshape(-1, 3)[finite]
    random = needs_random_init(len(points), config)
    if random:
        n = config.init_random_points
        points = (np.asarray(box_center) + rng.uniform(-box_half, box_half, size=(n, 3))).astype(np.float32)
        colors = rng.uniform(0, 1, size=(n, 3)).astype(np.float32)
    if config.init_max_points and len(points) > config.init_max_points:
        keep = rng.choice(len(points), config.init_max_points, replace=False)
        points = points[keep]
        colors = None if colors is None else colors[keep]
    if colors is None:
        colors = np.full_like(points, 0.5)
    n = len(points)
    log_s = knn_log_scales(points)
    if random:
        log_s = log_s + np.float32(np.log(config.random_init_scale))
    if config.init_scale_max > 0:
        log_s = np.minimum(log_s, np.float32(np.log(config.init_scale_max * extent)))
    k = (config.sh_degree + 1) ** 2 - 1
    logit = np.log(config.init_opacity / (1 - config.init_opacity))
    return Surfels(
        means=points,
        quats=random_quats(rng, n),
        log_scales=np.repeat(log_s[:, None], 2, axis=1),
        opacity_logits=np.full((n,), logit, np.float32),
        sh_dc=np.asarray(rgb_to_dc(np.clip(colors, 0, 1)), np.float32),
        sh_rest=np.zeros((n, k, 3), np.float32),
    )


def pad_params(s: Surfels, capacity: int) -> tuple[Surfels, np.ndarray]:
    """Host Surfels padded with empty slots to `capacity`, and the active mask."""
    s = s.to_numpy()
    if s.num > capacity:
        raise ValueError(f"{s.num} surfels do not fit a pool of capacity {capacity}")
    empty = empty_params(capacity - s.num, s.sh_degree)
    padded = jax.tree_util.tree_map(lambda a, b: np.concatenate([a, b], 0), s, empty)
    active = np.zeros(capacity, bool)
    active[: s.num] = True
    return padded, active


def new_state(params: Surfels, active, optimizers: dict, pose: PoseState | None = None,
              exposure: ExposureState | None = None) -> TrainState:
    from ghsplat_jax.train import optim

    params = jax.tree_util.tree_map(jnp.asarray, params)
    cap = params.num
    return TrainState(
        params=params,
        active=jnp.asarray(active, bool),
        opt_state=optim.init(optimizers, params),
        grad_accum=jnp.zeros(cap, jnp.float32),
        grad_count=jnp.zeros(cap, jnp.float32),
        max_radii=jnp.zeros(cap, jnp.float32),
        step=jnp.zeros((), jnp.int32),
        pose=pose,
        exposure=exposure,
    )


def _map_rows(tree, capacity: int, fn):
    """fn applied to every leaf with one row per pool slot (leading axis `capacity`); other
    leaves (the step, Adam's counts) pass through."""
    def one(leaf):
        if hasattr(leaf, "ndim") and leaf.ndim >= 1 and leaf.shape[0] == capacity:
            return fn(leaf)
        return leaf
    return jax.tree_util.tree_map(one, tree)


def _without_views(state: TrainState) -> TrainState:
    """The state without its per-view corrections: they have a row per view, not per pool slot."""
    return dataclasses.replace(state, pose=None, exposure=None)


def _with_views(state: TrainState, like: TrainState) -> TrainState:
    return dataclasses.replace(state, pose=like.pose, exposure=like.exposure)


def grow(state: TrainState, capacity: int) -> TrainState:
    """The same state in a larger pool (new slots empty, zero statistics and moments)."""
    old = state.capacity
    if capacity <= old:
        return state
    extra = capacity - old
    empty = empty_params(extra, state.params.sh_degree)
    params = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, jnp.asarray(b)], 0), state.params, empty)
    zeros = lambda leaf: jnp.concatenate([leaf, jnp.zeros((extra,) + leaf.shape[1:], leaf.dtype)], 0)  # noqa: E731
    rest = _map_rows(dataclasses.replace(_without_views(state), params=None), old, zeros)
    return _with_views(dataclasses.replace(rest, params=params), state)


def compact(state: TrainState, capacity: int) -> TrainState:
    """The same state in a pool of `capacity` slots, live rows first in their slot order (with
    their parameters, moments and statistics), then free ones. Every step's per-surfel work
    (projection, SH, Adam) scales with the pool, so a run whose count has stopped growing
    sheds its free slots this way."""
    active = np.asarray(state.active)
    live, free = np.flatnonzero(active), np.flatnonzero(~active)
    if capacity < len(live):
        raise ValueError(f"{len(live)} live surfels do not fit a pool of capacity {capacity}")
    rows = jnp.asarray(np.concatenate([live, free])[:min(capacity, state.capacity)])
    moved = _map_rows(_without_views(state), state.capacity, lambda leaf: leaf[rows])
    return grow(_with_views(moved, state), capacity)


def compiles_cost_more_than_slots() -> bool:
    """Whether buffers should grow for fewer recompiles rather than fewer spare slots: on an
    accelerator one recompile of the step (10-20 s on an H100) costs as much as a thousand fern
    steps, and spare slots cost little; on a CPU every slot adds work to every step."""
    return jax.default_backend() != "cpu"


def growth_bucket(n: int) -> int:
    """The size a growing buffer takes to hold `n`: the renderer's next bucket (1, 1.25, 1.5 or
    1.75 x 2^k, at most 25% spare) on a CPU, the next power of two on an accelerator, where
    each growth then at least doubles it (fern's pool grew 14 times in buckets on an H100)."""
    bucket = capacity_bucket(n)
    return 1 << (bucket - 1).bit_length() if compiles_cost_more_than_slots() else bucket


def fit_pool(state: TrainState) -> TrainState:
    """`state` compacted to the smallest pool bucket that holds its live surfels (the pair
    buffer's buckets, 1-1.75 x 2^k), or itself where that bucket is no smaller."""
    cap = capacity_bucket(state.num_active())
    return compact(state, cap) if cap < state.capacity else state


def render_params(params: Surfels, active: jax.Array, world_to_cam: jax.Array) -> Surfels:
    """Parameters to render: free slots are moved behind the camera (culled before binning,
    so they take no tile pairs) and made transparent; their gradients are zero."""
    R, t = world_to_cam[:3, :3], world_to_cam[:3, 3]
    center = -jnp.matmul(R.T, t, precision=FLOAT32)
    behind = center - R[2]  # one unit behind the camera along its optical axis
    a = active[:, None]
    return dataclasses.replace(
        params,
        means=jnp.where(a, params.means, behind),
        opacity_logits=jnp.where(active, params.opacity_logits, INACTIVE_LOGIT),
    )
