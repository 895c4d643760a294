"""sword-jax: style-robust video world models as simulators for VLA policy post-training.

Importing this package has no side effects: no JAX flags, no file I/O, no global config.
"""

__version__ = "0.1.0"
