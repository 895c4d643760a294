"""Score a folder of generated videos against a folder of real ones with the paper's metrics.

    python examples/score_video_folders.py REAL_DIR GENERATED_DIR [--metrics lpips,psnr,ssim,fvd] [--out scores.json]

Videos pair up by file name without its suffix (each name must be in both folders): ``.gif`` /
``.mp4`` / ``.avi`` (decoded with Pillow or OpenCV) or ``.npy`` (uint8 ``[T, H, W, 3]``). All videos must share one
frame size; each pair is cut to its shorter length, and all pairs to the shortest. Metrics
(:class:`sword_jax.metrics.suite.MetricSuite`): LPIPS (published AlexNet weights), PSNR, SSIM and
FloLPIPS per frame, FID and FVD over the set (FVD needs two clips of ``--fvd-clip-frames``; FID's
InceptionV3 ships with no package, so it runs with random weights unless
``SWORD_INCEPTION_WEIGHTS`` names a file, and the output says so). Without folders, two demo
folders are written first (moving squares as GIFs, and a noisy copy of them as ``.npy``).
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

VIDEO_SUFFIXES = (".gif", ".mp4", ".avi", ".npy")


def read_video(path: str) -> np.ndarray:
    """uint8 ``[T, H, W, 3]`` frames of one video file."""
    if path.endswith(".npy"):
        video = np.load(path, allow_pickle=False)
    elif path.endswith(".gif"):
        from PIL import Image, ImageSequence

        with Image.open(path) as image:
            frames = [(np.asarray(f.convert("RGB")), f.info.get("duration") or 0) for f in ImageSequence.Iterator(image)]
        # GIF writers merge repeated frames into one longer frame: repeat them back at the shortest duration
        shortest = min((d for _, d in frames if d > 0), default=0)
        video = np.stack([f for f, d in frames for _ in range(max(1, round(d / shortest)) if shortest else 1)])
    else:
        import cv2

        capture, frames = cv2.VideoCapture(path), []
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
        capture.release()
        video = np.stack(frames) if frames else np.zeros((0, 0, 0, 3), np.uint8)
    if video.dtype != np.uint8 or video.ndim != 4 or video.shape[-1] != 3 or len(video) == 0:
        raise ValueError(f"{path}: expected uint8 frames [T, H, W, 3], got {video.dtype} {video.shape}")
    return video


def read_pairs(real_dir: str, generated_dir: str) -> tuple[list[str], np.ndarray, np.ndarray]:
    """``(names, real [N, T, H, W, 3], generated [N, T, H, W, 3])`` in [0, 1], paired by file name."""
    files = {}
    for folder in (real_dir, generated_dir):
        if not os.path.isdir(folder):
            raise SystemExit(f"score_video_folders: {folder} is not a folder")
        files[folder] = {os.path.splitext(f)[0]: os.path.join(folder, f) for f in sorted(os.listdir(folder))
                         if f.lower().endswith(VIDEO_SUFFIXES)}
    names = sorted(set(files[real_dir]) & set(files[generated_dir]))
    unpaired = sorted(set(files[real_dir]) ^ set(files[generated_dir]))
    if unpaired or not names:
        raise SystemExit(f"score_video_folders: videos must pair up by file name; unpaired: {unpaired or 'no videos'}")
    pairs = [(read_video(files[real_dir][n]), read_video(files[generated_dir][n])) for n in names]
    sizes = {v.shape[1:] for pair in pairs for v in pair}
    if len(sizes) != 1:
        raise SystemExit(f"score_video_folders: all videos must share one frame size, got {sorted(sizes)}")
    length = min(len(v) for pair in pairs for v in pair)
    real, generated = (np.stack([pair[i][:length] for pair in pairs]).astype(np.float32) / 255.0 for i in (0, 1))
    return names, real, generated


def write_demo_folders(root: str) -> tuple[str, str]:
    """Moving squares as GIFs, and the same videos with Gaussian noise as ``.npy``."""
    import jax
    from PIL import Image

    from sword_jax.vae.train import moving_squares

    real = np.asarray(moving_squares(key=jax.random.key(0), batch=3, frames=17, size=64)) * 127.5 + 127.5
    noisy = real + np.random.default_rng(0).normal(0.0, 25.0, real.shape)
    real, noisy = (np.clip(np.rint(v), 0, 255).astype(np.uint8) for v in (real, noisy))
    folders = (os.path.join(root, "real"), os.path.join(root, "generated"))
    for folder in folders:
        os.makedirs(folder, exist_ok=True)
    for i in range(len(real)):
        frames = [Image.fromarray(frame) for frame in real[i]]
        frames[0].save(os.path.join(folders[0], f"video{i}.gif"), save_all=True, append_images=frames[1:],
                       duration=125, loop=0)
        np.save(os.path.join(folders[1], f"video{i}.npy"), noisy[i])
    return folders


def main(argv=None) -> dict:
    from sword_jax.metrics.config import EvalConfig
    from sword_jax.metrics.suite import ALL_METRICS, MetricSuite

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("real", nargs="?", help="folder of real videos (default: write demo folders)")
    parser.add_argument("generated", nargs="?", help="folder of generated videos, same file names")
    parser.add_argument("--metrics", default="lpips,psnr,ssim", help=f"comma list of {','.join(ALL_METRICS)}")
    parser.add_argument("--fvd-clip-frames", type=int, default=16)
    parser.add_argument("--demo-dir", default="runs/examples-videos", help="where the demo folders go")
    parser.add_argument("--out", default="", help="also write the scores as JSON here")
    args = parser.parse_args(argv)
    if bool(args.real) != bool(args.generated):
        parser.error("give both folders, or neither for the demo")
    real_dir, generated_dir = (args.real, args.generated) if args.real else write_demo_folders(args.demo_dir)

    metrics = tuple(m for m in args.metrics.split(",") if m)
    if unknown := set(metrics) - set(ALL_METRICS):
        parser.error(f"unknown metrics {sorted(unknown)}; known: {','.join(ALL_METRICS)}")
    names, real, generated = read_pairs(real_dir, generated_dir)
    config = EvalConfig(fvd_clip_frames=args.fvd_clip_frames, allow_random_weights_for=("fid",))
    suite = MetricSuite(config, metrics=metrics)
    scores = suite.evaluate(real, generated).overall
    result = {"videos": names, "frames": int(real.shape[1]), "scores": scores, "weights": suite.describe_weights(),
              "random_weight_networks": suite.random_weight_networks}
    print(json.dumps(result, indent=1))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    main()
