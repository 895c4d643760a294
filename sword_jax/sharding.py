"""Logical axis names, the rules mapping them to mesh axes, mesh construction and sharded init.

Model code names *logical* axes only (``batch``, ``embed``, ``heads`` ...). One table of rules,
set in the config, maps each logical name to zero or more of the physical mesh axes
``data``, ``fsdp`` and ``tensor``. Nothing here touches global JAX state.

Parameters are annotated with ``nnx.with_partitioning(init, ("embed", "mlp"))``; the helpers
below read that metadata (the ``out_sharding`` field of an ``nnx.Variable``), translate it through
the rules and build ``NamedSharding`` trees, so parameters are born sharded:
``jax.eval_shape(init)`` -> shardings -> ``jax.jit(init, out_shardings=...)``.

Batches of a multi-process job are global arrays assembled from each process's rows: a loader
makes only the rows its devices hold (:func:`rows_held`) and :func:`to_global` places them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from flax import nnx
from flax.core import spmd as flax_spmd
from jax.sharding import Mesh, NamedSharding, PartitionSpec

MESH_AXES: tuple[str, ...] = ("data", "fsdp", "tensor")

# Every logical axis name used anywhere in sword_jax. Declared once, here.
LOGICAL_AXES: tuple[str, ...] = (
    "batch",  # samples of a batch
    "episodes",  # episodes of the latent cache / dataset
    "group",  # GRPO trajectories of one start state
    "time",  # video or latent frames
    "length",  # token sequence
    "height",
    "width",
    "channels",  # image / latent channels
    "embed",  # model width
    "heads",  # attention heads
    "head_dim",
    "mlp",  # feed-forward hidden width
    "modulation",  # AdaLN slots
    "layers",  # stacked (scanned) blocks
    "conv_in",
    "conv_out",
    "kernel",  # spatial / temporal kernel taps
    "action",  # action dimensions
)

# The default table: data parallel + FSDP on the batch, FSDP over model width, tensor
# parallel over heads and the MLP hidden width.
DEFAULT_RULES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("batch", ("data", "fsdp")),
    ("episodes", ("data", "fsdp")),
    ("group", ()),
    ("time", ()),
    ("length", ()),
    ("height", ()),
    ("width", ()),
    ("channels", ()),
    ("embed", ("fsdp",)),
    ("heads", ("tensor",)),
    ("head_dim", ()),
    ("mlp", ("tensor",)),
    ("modulation", ()),
    ("layers", ()),
    ("conv_in", ()),
    ("conv_out", ("fsdp",)),
    ("kernel", ()),
    ("action", ()),
)


@dataclasses.dataclass(frozen=True)
class MeshConfig:
    """Physical mesh shape and the logical -> mesh axis table.

    Attributes:
      data: size of the ``data`` axis; -1 means "all remaining devices".
      fsdp: size of the ``fsdp`` axis; -1 means "all remaining devices".
      tensor: size of the ``tensor`` axis; -1 means "all remaining devices".
      rules: (logical name, mesh axes) pairs; a logical name missing here is replicated.
      distributed: call ``jax.distributed.initialize()`` in the entry point (multi-host).
    """

    data: int = -1
    fsdp: int = 1
    tensor: int = 1
    rules: tuple[tuple[str, tuple[str, ...]], ...] = DEFAULT_RULES
    distributed: bool = False

    def validate(self) -> None:
        sizes = (self.data, self.fsdp, self.tensor)
        if sum(s == -1 for s in sizes) > 1:
            raise ValueError(f"mesh: at most one of data/fsdp/tensor may be -1, got {sizes}")
        for name, size in zip(MESH_AXES, sizes):
            if size == 0 or size < -1:
                raise ValueError(f"mesh.{name} must be a positive size or -1, got {size}")
        for logical, axes in self.rules:
            if logical not in LOGICAL_AXES:
                raise ValueError(f"mesh.rules: unknown logical axis {logical!r}; known: {LOGICAL_AXES}")
            for axis in axes:
                if axis not in MESH_AXES:
                    raise ValueError(f"mesh.rules[{logical!r}]: unknown mesh axis {axis!r}; known: {MESH_AXES}")


def mesh_shape(cfg: MeshConfig, num_devices: int) -> tuple[int, int, int]:
    """Resolves -1 in the config to a concrete (data, fsdp, tensor) shape for ``num_devices``."""
    cfg.validate()
    sizes = [cfg.data, cfg.fsdp, cfg.tensor]
    known = math.prod(s for s in sizes if s != -1)
    if -1 in sizes:
        if num_devices % known:
            raise ValueError(
                f"mesh: {num_devices} devices are not divisible by the fixed axes "
                f"{dict(zip(MESH_AXES, sizes))} (product {known})"
            )
        sizes[sizes.index(-1)] = num_devices // known
    if math.prod(sizes) != num_devices:
        raise ValueError(
            f"mesh: data*fsdp*tensor = {math.prod(sizes)} but {num_devices} devices are available "
            f"({dict(zip(MESH_AXES, sizes))})"
        )
    return tuple(sizes)  # type: ignore[return-value]


def make_mesh(cfg: MeshConfig, devices: Sequence[jax.Device] | None = None) -> Mesh:
    """Builds a (data, fsdp, tensor) mesh over ``devices`` (default: all devices)."""
    devices = list(jax.devices() if devices is None else devices)
    shape = mesh_shape(cfg, len(devices))
    try:
        device_array = jax.experimental.mesh_utils.create_device_mesh(shape, devices=devices)
    except Exception:  # noqa: BLE001 - fall back to plain order for unusual topologies
        device_array = np.asarray(devices, dtype=object).reshape(shape)
    return Mesh(device_array, MESH_AXES)


def logical_to_spec(
    logical_axes: Sequence[str | None] | None,
    rules: Sequence[tuple[str, Sequence[str]]],
    mesh: Mesh | None = None,
    shape: Sequence[int] | None = None,
) -> PartitionSpec:
    """Translates logical axis names into a ``PartitionSpec`` of mesh axes.

    A mesh axis is used at most once per spec (first claim wins). With ``mesh`` and ``shape``
    given, a dimension not divisible by its mesh axes' size is left replicated, so tiny test
    shapes work on any mesh.
    """
    if logical_axes is None:
        return PartitionSpec()
    table = {name: tuple(axes) for name, axes in rules}
    used: set[str] = set()
    spec: list[Any] = []
    for dim, name in enumerate(logical_axes):
        axes = tuple(a for a in table.get(name, ()) if a not in used) if name else ()
        if mesh is not None:
            axes = tuple(a for a in axes if mesh.shape[a] > 1)
            if shape is not None and axes:
                size = math.prod(mesh.shape[a] for a in axes)
                if shape[dim] % size:
                    axes = ()
        used.update(axes)
        spec.append(None if not axes else axes[0] if len(axes) == 1 else axes)
    while spec and spec[-1] is None:
        spec.pop()
    return PartitionSpec(*spec)


def logical_sharding(
    mesh: Mesh,
    logical_axes: Sequence[str | None],
    rules: Sequence[tuple[str, Sequence[str]]],
    shape: Sequence[int] | None = None,
) -> NamedSharding:
    """``NamedSharding`` for an array whose dims carry the given logical names."""
    return NamedSharding(mesh, logical_to_spec(logical_axes, rules, mesh, shape))


def _variable_logical_axes(variable: nnx.Variable) -> tuple[str | None, ...] | None:
    metadata = variable.get_metadata()
    for key in ("out_sharding", "sharding_names", "sharding"):
        axes = metadata.get(key)
        if axes is not None:
            return tuple(axes)
    return None


def state_shardings(
    abstract_state: Any, mesh: Mesh, rules: Sequence[tuple[str, Sequence[str]]]
) -> Any:
    """Maps an (abstract) ``nnx.State`` to a matching tree of ``NamedSharding``.

    Variables without partitioning metadata are replicated.
    """

    def one(variable):
        if isinstance(variable, nnx.Variable):
            value = variable.get_value() if hasattr(variable, "get_value") else variable.value
            spec = logical_to_spec(_variable_logical_axes(variable), rules, mesh, value.shape)
            return variable.replace(NamedSharding(mesh, spec))
        return NamedSharding(mesh, PartitionSpec())

    return jax.tree.map(one, abstract_state, is_leaf=lambda x: isinstance(x, nnx.Variable))


def abstract_module(factory: Callable[[], nnx.Module]) -> nnx.Module:
    """Builds a module of ``ShapeDtypeStruct`` leaves without allocating anything."""
    with nnx.use_eager_sharding(False):
        return nnx.eval_shape(factory)


def create_sharded(
    factory: Callable[[], nnx.Module],
    mesh: Mesh,
    rules: Sequence[tuple[str, Sequence[str]]],
) -> tuple[nnx.GraphDef, nnx.State]:
    """Creates a module's state directly in its sharded layout.

    Args:
      factory: builds the module; it must take its randomness from inside (e.g. ``nnx.Rngs(seed)``).
      mesh: the device mesh.
      rules: logical -> mesh axis table.

    Returns:
      ``(graphdef, state)`` with every parameter placed by its logical annotation.
    """
    graphdef, abstract_state = nnx.split(abstract_module(factory))
    shardings = state_shardings(abstract_state, mesh, rules)

    def init():
        with nnx.use_eager_sharding(False):
            return nnx.split(factory())[1]

    state = jax.jit(init, out_shardings=shardings)()
    return graphdef, state


def create(
    factory: Callable[[], nnx.Module],
    mesh: Mesh | None = None,
    rules: Sequence[tuple[str, Sequence[str]]] = DEFAULT_RULES,
) -> tuple[nnx.GraphDef, nnx.State]:
    """``(graphdef, state)`` of a fresh module: born sharded over ``mesh`` (:func:`create_sharded`), or, without
    one, created unsharded on the default device."""
    if mesh is not None:
        return create_sharded(factory, mesh, rules)
    with nnx.use_eager_sharding(False):
        return nnx.split(factory())


def active_rules() -> Sequence[tuple[str, Sequence[str]]]:
    """The rules of the innermost :func:`use_mesh` (Flax's ``logical_axis_rules`` context), else
    ``DEFAULT_RULES``."""
    return flax_spmd.get_logical_axis_rules() or DEFAULT_RULES


def constrain(x: jax.Array, logical_axes: Sequence[str | None], rules=None) -> jax.Array:
    """Activation sharding constraint by logical names, a no-op outside a mesh context.

    Reads JAX's own mesh context (``jax.sharding.get_abstract_mesh()``, set by :func:`use_mesh` or
    ``jax.set_mesh``), so a jitted function traced inside a mesh and outside it are two traces, and
    the rules of :func:`use_mesh` (default: ``DEFAULT_RULES``).
    """
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty or mesh.size == 1:
        return x
    spec = logical_to_spec(logical_axes, rules or active_rules(), mesh, x.shape)
    return jax.lax.with_sharding_constraint(x, spec)


@contextlib.contextmanager
def use_mesh(mesh: Mesh, rules: Sequence[tuple[str, Sequence[str]]] = DEFAULT_RULES):
    """Context in which :func:`constrain` shards activations over ``mesh`` with ``rules``.

    Enters ``jax.set_mesh(mesh)`` (outside ``jax.jit`` only) and Flax's ``logical_axis_rules``; the
    rules are not part of a jit's cache key, so a function jitted once should be called under one
    table (the compiled steps of :func:`compile_step` always are).
    """
    with jax.set_mesh(mesh), flax_spmd.logical_axis_rules(tuple(rules)):
        yield mesh


def shardings_on(tree: Any, mesh: Mesh) -> Any:
    """Each array leaf's ``NamedSharding`` if it lives on ``mesh``, else replicated over ``mesh``."""

    def one(x):
        sharding = getattr(x, "sharding", None)
        if isinstance(sharding, NamedSharding) and sharding.mesh == mesh:
            return sharding
        return replicated(mesh)

    return jax.tree.map(one, tree)


def leading_axis_shardings(tree: Any, mesh: Mesh, rules=DEFAULT_RULES, leading: str = "batch") -> Any:
    """Shards every array leaf's leading dim as ``leading`` (replicated where it does not divide)."""
    return jax.tree.map(
        lambda x: logical_sharding(mesh, (leading,) + (None,) * (np.ndim(x) - 1), rules, np.shape(x))
        if np.ndim(x) else replicated(mesh), tree)


def place(tree: Any, shardings: Any, *, donate: bool = False) -> Any:
    """``tree`` re-made by a jit with ``out_shardings``: the arrays' types then record the mesh as
    a compiled step's outputs do (see :func:`settle`). An array on devices other than its target's
    (weights restored onto one device, placed over a mesh) goes through the host: a jit takes no mix of
    arrays committed to different devices."""
    tree = jax.tree.map(lambda x, s: np.asarray(jax.device_get(x)) if isinstance(x, jax.Array)
                        and x.sharding.device_set != s.device_set else x, tree, shardings)
    return jax.jit(lambda t: t, out_shardings=shardings, donate_argnums=(0,) if donate else ())(tree)


def default_mesh(mesh: Mesh | None) -> Mesh:
    """``mesh``, or a one-device mesh (the first device) for callers that pass none."""
    return mesh if mesh is not None else make_mesh(MeshConfig(data=1), jax.devices()[:1])


def compile_step(
    step_fn: Callable[[Any, Any, jax.Array], tuple[Any, Any]],
    mesh: Mesh,
    rules: Sequence[tuple[str, Sequence[str]]] = DEFAULT_RULES,
    *,
    state_shardings: Any = None,
    batch_shardings: Any = None,
    donate: bool = True,
) -> Callable[[Any, Any, jax.Array], tuple[Any, Any]]:
    """``step(state, batch, key) -> (state, metrics)`` jitted with explicit in/out shardings, the
    state donated, and traced inside :func:`use_mesh` so :func:`constrain` shards activations.

    Args:
      step_fn: the pure step.
      mesh, rules: the device mesh and the logical -> mesh axis table.
      state_shardings: the state's shardings (in and out); ``None``: taken from the first state
        passed (:func:`shardings_on`: leaves already on ``mesh`` keep theirs, others are replicated).
      batch_shardings: a tree of shardings, a function ``batch -> shardings``, or ``None``: the
        leading dim of every batch leaf is ``batch`` (:func:`leading_axis_shardings`).
      donate: donate the state (argument 0).

    The first call places the state at its shardings (:func:`place`), so the step's input and
    output types agree and it traces once; metrics come back replicated. ``call.lower(state, batch,
    key)`` lowers it inside the mesh (``.compile().input_shardings`` etc.); ``call.jitted(batch,
    state)`` is the underlying ``jax.jit`` for a batch's structure.
    """
    replicated_sharding = replicated(mesh)
    compiled: dict[Any, Any] = {}
    placed = [False]
    state_tree = [state_shardings]

    def batch_tree(batch):
        if batch_shardings is None:
            return leading_axis_shardings(batch, mesh, rules)
        return batch_shardings(batch) if callable(batch_shardings) else batch_shardings

    def jitted(batch, state=None):
        if state_tree[0] is None:
            state_tree[0] = shardings_on(state, mesh)
        shardings = batch_tree(batch)
        cache_key = (jax.tree.structure(batch), tuple(jax.tree.leaves(shardings)))
        if cache_key not in compiled:
            compiled[cache_key] = jax.jit(
                step_fn,
                in_shardings=(state_tree[0], shardings, replicated_sharding),
                out_shardings=(state_tree[0], replicated_sharding),
                donate_argnums=(0,) if donate else (),
            )
        return compiled[cache_key]

    def call(state, batch, key):
        fn = jitted(batch, state)
        if not placed[0]:
            state, placed[0] = place(state, state_tree[0], donate=donate), True
        with use_mesh(mesh, rules):
            return fn(state, batch, key)

    def lower(state, batch, key):
        with use_mesh(mesh, rules):
            return jitted(batch, state).lower(state, batch, key)

    call.jitted, call.lower = jitted, lower  # type: ignore[attr-defined]
    return call


def batch_sharding(mesh: Mesh, ndim: int, rules=DEFAULT_RULES, leading: str = "batch") -> NamedSharding:
    """Sharding of an array whose leading dim is ``leading`` (batch or episodes), rest replicated."""
    return NamedSharding(mesh, logical_to_spec((leading,) + (None,) * (ndim - 1), rules, mesh))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def settle(tree: Any) -> Any:
    """The same arrays, re-made by an identity ``jax.jit`` with their own shardings (donated).

    From jax 0.11 an array's abstract type records the mesh of the ``NamedSharding`` a jitted
    function gave it; arrays made otherwise (``device_put``, eager ops, a checkpoint restore, a jit
    without ``out_shardings``) record none. A train step fed such a state returns one whose types
    differ, so its second call traces and compiles again. Settling the state once before the loop
    makes the step's input and output types equal. Older JAX: a no-op copy. Leaves that are not
    arrays with a ``NamedSharding`` pass through unchanged.
    """
    leaves, treedef = jax.tree.flatten(tree)
    index = [i for i, x in enumerate(leaves) if isinstance(x, jax.Array) and isinstance(x.sharding, NamedSharding)]
    if index:
        chosen = [leaves[i] for i in index]
        settled = jax.jit(lambda t: t, out_shardings=[x.sharding for x in chosen], donate_argnums=0)(chosen)
        for i, x in zip(index, settled):
            leaves[i] = x
    return jax.tree.unflatten(treedef, leaves)


def put(value: Any, target: NamedSharding) -> jax.Array:
    """Places a host value (or a typed PRNG key) as a global array with ``target`` sharding.

    Works on one process and across hosts (each process materialises only its own shards), where
    ``jax.device_put`` refuses a sharding that spans non-addressable devices.
    """
    if isinstance(value, jax.Array) and jax.dtypes.issubdtype(value.dtype, jax.dtypes.prng_key):
        data = put(np.asarray(jax.random.key_data(value)), target)
        impl = jax.random.key_impl(value)
        return jax.jit(lambda d: jax.random.wrap_key_data(d, impl=impl), out_shardings=target)(data)
    host = np.asarray(value)
    return jax.make_array_from_callback(host.shape, target, lambda index: host[index])


def rows_held(sharding: jax.sharding.Sharding, batch_size: int, devices=None) -> np.ndarray:
    """The rows (ascending) of a ``[batch_size]`` array with ``sharding`` that ``devices`` (default: this
    process's) hold: all of them on one process, this process's part on several."""
    held = sharding.addressable_devices if devices is None else set(devices)
    rows = set()
    for device, (index,) in sharding.devices_indices_map((batch_size,)).items():
        if device in held:
            rows.update(range(*index.indices(batch_size)))
    return np.asarray(sorted(rows), np.int64)


def batch_shards(sharding: NamedSharding) -> int:
    """How many row blocks ``sharding`` splits an array's leading dim into (1: replicated)."""
    axes = sharding.spec[0] if len(sharding.spec) else None
    axes = () if axes is None else (axes,) if isinstance(axes, str) else tuple(axes)
    return math.prod(sharding.mesh.shape[axis] for axis in axes)


def check_batch_divides(sharding: NamedSharding, batch_size: int, name: str) -> None:
    """Refuses a global batch whose rows do not split evenly over the devices ``sharding`` shards it over.

    Raises:
      ValueError: naming ``name``, the batch size, the devices it is split over, the mesh and the processes.
    """
    shards, processes = batch_shards(sharding), jax.process_count()
    if batch_size < 1 or batch_size % shards:
        in_processes = f"{processes} process{'es' if processes > 1 else ''}"
        raise ValueError(
            f"{name}={batch_size} does not split over the {shards} devices its rows are sharded over (mesh "
            f"{dict(sharding.mesh.shape)}, {sharding.mesh.size} devices in {in_processes}): use a multiple of {shards}")


def to_global(batch: dict[str, np.ndarray], shardings: dict[str, Any], rows: np.ndarray | None = None,
              batch_size: int | None = None) -> dict[str, jax.Array]:
    """Host batch -> global arrays, each process materialising only its own devices' slices.

    Args:
      batch: the whole batch, or with ``rows`` only those rows of it (what this process holds).
      shardings: each entry's sharding.
      rows: the global row of each host row (ascending, :func:`rows_held`); ``None``: all rows.
      batch_size: the global batch size (with ``rows``).
    """
    if rows is None or len(rows) == batch_size:
        return {name: put(value, shardings[name]) for name, value in batch.items()}

    def local(value: np.ndarray, index: tuple) -> np.ndarray:
        wanted = np.arange(batch_size)[index[0]]
        at = np.searchsorted(rows, wanted)
        if np.any(at >= len(rows)) or np.any(rows[np.minimum(at, len(rows) - 1)] != wanted):
            raise ValueError(f"to_global: a device of this process needs rows {wanted.tolist()}, "
                             f"but it holds {rows.tolist()}")
        return value[at][(slice(None), *index[1:])]

    return {name: jax.make_array_from_callback((batch_size, *value.shape[1:]), shardings[name],
                                               lambda index, value=value: local(value, index))
            for name, value in batch.items()}


class RowLoader:
    """One array's batches in a job of one or several processes: :meth:`host_batch_at` makes only the rows of a
    step's batch that this process's devices hold (``rows``), :meth:`place` assembles the global
    ``{field: [B, ...]}`` from every process's rows (:func:`to_global`).

    Args:
      rows_at: ``rows_at(step, rows) -> [len(rows), ...]``, those rows of the 0-based step's batch; a pure function
        of both (exact resume), each row the same whichever rows are asked for.
      batch_size: the global batch size ``B``.
      mesh, rules: the rows are split over the mesh axes of the ``batch`` logical axis, as the step's input.
      field, ndim: the batch's one key and its array's rank.
      name: the setting that gives ``batch_size`` (named by the refusal).
      devices: whose rows to make (default: this process's devices).

    Raises:
      ValueError: ``batch_size`` does not split evenly over the devices the rows are sharded over
        (:func:`check_batch_divides`).
    """

    def __init__(self, rows_at: Callable[[int, np.ndarray], np.ndarray], batch_size: int, mesh: Mesh,
                 rules=DEFAULT_RULES, *, field: str, ndim: int, name: str, devices: Sequence[jax.Device] | None = None):
        self.rows_at, self.batch_size, self.field = rows_at, batch_size, field
        self.sharding = batch_sharding(mesh, ndim, rules)
        check_batch_divides(self.sharding, batch_size, name)
        self.rows = rows_held(self.sharding, batch_size, devices)  # the only rows this process makes

    def host_batch_at(self, step: int) -> np.ndarray:
        """This process's rows (``rows``) of step ``step``'s batch (0-based); on one process, the whole batch."""
        return self.rows_at(step, self.rows)

    def place(self, value: np.ndarray) -> dict[str, jax.Array]:
        """This process's rows (:meth:`host_batch_at`) -> ``{field: global [B, ...]}``."""
        return to_global({self.field: value}, {self.field: self.sharding}, self.rows, self.batch_size)
