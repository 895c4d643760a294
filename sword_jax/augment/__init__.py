"""sword_jax.augment: structure-guided style augmentation and the LIBERO-Original / LIBERO-Mixed splits.

Conventions: frames float in [0, 1] ``[T, H, W, 3]`` (``transforms.to_unit_range`` /
``to_signed_range`` convert from uint8 / to the VAE's [-1, 1]); depth metres ``[T, H, W]``
(non-finite = far); segmentation an integer class map ``[T, H, W]`` grouped by
``style.SegClasses`` (renderer scenes: ``SegClasses.from_class_names(scene.class_names, fixtures)``).

Modules:
  ``config``: :class:`AugmentConfig` (the ``augment`` config section).
  ``style``: ``Style`` / ``RegionStyle`` pytrees, ``sample_style(key, split)``, ``sample_styles``,
      ``identity_style``; the disjoint training / held-out split (``assert_training_style``,
      ``split_violations``, ``style_split``, ``HeldOutStyleError``); ``SegClasses``.
  ``transforms``: ``augment(frames, depth, seg, style, *, key, intensity, classes, fov_deg)``
      (pure, jittable, vmappable), ``augment_batch`` (many episodes) and ``augment_styles`` (one episode,
      many styles), both mapped, and the individual transforms.
  ``textures``: depth -> camera points / normals; procedural textures.
  ``structure``: edge-F1, segmentation-boundary and depth-edge recall (``structure_scores``).
  ``pipeline``: ``make_step_augmenter`` (per step, on device), ``make_styled_copies`` /
      ``encode_styled_copies`` (pre-encoded copies; what the pipeline uses, with the measurement behind it).
  ``eval_splits``: ``build_eval_splits(episodes, *, seed)`` -> LIBERO-Original / LIBERO-Mixed.
  ``ingest``: ``load_styled_episodes(path, originals)`` for episodes styled elsewhere.
  ``episodes``: the ``Episodes`` container and ``as_episodes`` validation.
  ``synthetic``: a tiny synthetic tabletop scene; ``gallery``: the style gallery PNG.
"""
