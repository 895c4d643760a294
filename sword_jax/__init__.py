"""sword-jax: style-robust video world models as simulators for VLA policy post-training.

The public API (:mod:`sword_jax.api`) is re-exported here, imported on first use::

    import sword_jax
    model = sword_jax.load_world_model("runs/sword-tiny")
    video = sword_jax.rollout(model, given_frames, actions, key=jax.random.key(0))

Importing this package has no side effects: no JAX flags, no file I/O, no global config, and no
import of JAX itself until one of the names below is used.
"""

__version__ = "0.1.0"

_API = (
    "CheckpointError", "LoadedWorldModel", "WorldModelSpec", "decode", "encode", "learned_simulator",
    "load_reward_model", "load_world_model", "make_env", "make_vector_env", "rollout", "rollout_latents",
    "start_states",
)

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        from sword_jax import api

        return getattr(api, name)
    raise AttributeError(f"module 'sword_jax' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_API))
