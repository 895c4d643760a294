"""Command lines: one-line errors with exit status 2 (usage) or 1 (runtime), --debug, --help, --print-config."""

import ast
import importlib
import os
import subprocess
import sys

import pytest

import configs
from configs.cli import ConfigError, apply_overrides, flatten, format_config
from sword_jax import cli

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# Every entry point with a bad command line that fails before any work.
BAD_ARGS = {
    "train.pipeline": ["--modle.num_layers=2"],
    "train.compare": ["--runs", "nope"],
    "train.gen_data": ["--task", "12", "--out", "unused.hdf5"],
    "train.train_vae": ["--trainer.steps=abc"],
    "train.train_light_decoder": ["--light_decoder.width=0", "--latents", "unused.npz"],
    "train.train_world_model": ["--synthetic", "--no-such-flag"],
    "train.evaluate_world_model": ["--config", "sword:huge"],
    "train.train_policy": ["--model.num_layers=0"],
    "train.train_reward": ["--demos"],
    "train.train_probe": ["--demos"],
    "train.grpo": ["--simulator", "real"],
    "train.gallery": ["--out", "unused.png", "--size", "8"],
    "train.launch": ["--processes", "2", "--", "python", "-m", "train.grpo"],
    "train.convert_wan22": ["check"],
    "train.bundle": ["pack", "run", "out", "--part-mib", "many"],
    "train.encode_latents": ["--out"],
    "train.verify_metrics": [],
}
# Every entry point: each module of train/ but the process setup they share.
ENTRY_POINTS = sorted(f"train.{name[:-3]}" for name in os.listdir(os.path.join(ROOT, "train"))
                      if name.endswith(".py") and name not in ("__init__.py", "distributed.py"))


def _run(main, argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.run(main, argv)
    out, err = capsys.readouterr()
    return exit_info.value.code, out, err


@pytest.mark.parametrize("module_name", sorted(BAD_ARGS))
def test_entry_point_bad_arguments_give_one_line_and_status_2(module_name, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    module = importlib.import_module(module_name)
    code, _, err = _run(module.main, BAD_ARGS[module_name], capsys)
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert "error:" in err


def test_bad_arguments_cover_the_entry_points():
    """Those missing answer usage errors their own way (``train.score_metrics``: ``score: ...``, status 2)."""
    assert set(BAD_ARGS) <= set(ENTRY_POINTS) and set(ENTRY_POINTS) - set(BAD_ARGS) == {"train.score_metrics"}


@pytest.mark.parametrize("module_name", ENTRY_POINTS)
def test_entry_point_main_block_goes_through_run(module_name):
    """``python -m <module>`` must reach ``main`` through ``sword_jax.cli.run``."""
    path = os.path.join(ROOT, *module_name.split(".")) + ".py"
    with open(path) as f:
        tree = ast.parse(f.read())
    blocks = [node for node in tree.body if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test)]
    assert len(blocks) == 1
    calls = [ast.unparse(node.func) for node in ast.walk(blocks[0]) if isinstance(node, ast.Call)]
    run_names = {"cli.run"} | {alias.asname or alias.name for node in ast.walk(tree)
                               if isinstance(node, ast.ImportFrom) and node.module == "sword_jax.cli"
                               for alias in node.names if alias.name == "run"}
    assert any(call in run_names for call in calls), calls


def test_missing_checkpoint_is_one_line_and_status_1(capsys, tmp_path, monkeypatch):
    from train import evaluate_world_model

    monkeypatch.chdir(tmp_path)
    code, _, err = _run(evaluate_world_model.main, ["--synthetic", "--model", f"m={tmp_path / 'no_run'}"], capsys)
    assert code == 1 and "Traceback" not in err, err
    assert err.strip() == f"{cli._prog()}: error: {tmp_path / 'no_run'} does not exist"  # the path as given
    assert not (tmp_path / "no_run").exists()  # reading never creates directories


def test_pipeline_command_line_in_a_subprocess():
    """The issue's example, end to end: message alone on stderr, status 2; --debug keeps the traceback."""
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    command = [sys.executable, "-m", "train.pipeline", "--modle.num_layers=2"]
    plain = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    debug = subprocess.Popen(command + ["--debug"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    out, err = plain.communicate(timeout=120)
    assert plain.returncode == 2 and out == ""
    assert err.strip() == ("train.pipeline: error: unknown config key 'modle.num_layers'; sections are: augment, "
                           "cache, data, eval, flow, light_decoder, mesh, model, name, rl, seed, sim, trainer, vae, "
                           "workdir"), err
    _, err = debug.communicate(timeout=120)
    assert debug.returncode == 2 and "Traceback" in err and err.strip().endswith("workdir"), err


def test_run_exit_statuses_and_debug(capsys):
    class DatasetLikeError(ValueError):
        pass

    def usage(argv):
        raise ConfigError("unknown config key 'x'")

    def deliberate(argv):
        raise SystemExit("train_x: pass --episodes")

    def runtime(argv):
        raise DatasetLikeError("broken.hdf5 is truncated")

    def bug(argv):
        raise KeyError("oops")

    assert _run(usage, [], capsys)[::2] == (2, f"{cli._prog()}: error: unknown config key 'x'\n")
    assert _run(deliberate, [], capsys)[::2] == (1, "train_x: pass --episodes\n")
    with pytest.raises(SystemExit) as exit_info:
        cli.run(runtime, [], runtime_errors=(DatasetLikeError,))
    assert exit_info.value.code == 1 and "truncated" in capsys.readouterr().err
    with pytest.raises(DatasetLikeError):  # not declared: a bug, with its traceback
        cli.run(runtime, [])
    with pytest.raises(KeyError):
        cli.run(bug, ["--debug"])
    code, _, err = _run(usage, ["--debug"], capsys)
    assert code == 2 and "Traceback" in err and err.strip().splitlines()[-1].endswith("unknown config key 'x'")
    seen = []
    assert _run(lambda argv: seen.append(argv) or 3, ["--a", "--debug", "b"], capsys)[0] == 3
    assert seen == [["--a", "b"]]
    assert _run(lambda argv: {"done": True}, [], capsys)[0] == 0


def test_runtime_error_names_resolve():
    """Every named runtime error exists (a rename would silently bring tracebacks back)."""
    for name in cli.RUNTIME_ERRORS:
        module_name, _, cls_name = name.rpartition(".")
        assert issubclass(getattr(importlib.import_module(module_name), cls_name), Exception), name


def test_help_documents_the_configuration(capsys):
    from train import pipeline

    code, out, _ = _run(pipeline.main, ["--help"], capsys)
    assert code == 0
    unwrapped = "".join(out.split())  # argparse wraps lines at spaces and hyphens
    for needle in ("sword:tiny|small|paper", "cache_ablation:linear-direct-single|", "--workdirDIR",
                   "--print-config", "--SECTION.KEY=VALUE", "--debug", "--stop-after"):
        assert needle in unwrapped, needle


def test_print_config_lists_every_key_and_round_trips(capsys):
    from train import train_reward

    code, out, _ = _run(train_reward.main, ["--config", "cache_ablation:tf", "--print-config", "--model.num_layers=3"],
                        capsys)
    assert code == 0
    lines = out.strip().splitlines()
    assert lines[0] == "# cache_ablation:tf"
    cfg = apply_overrides(configs.get("cache_ablation:tf"), ["--model.num_layers=3"])
    assert [line.split("=", 1)[0][2:] for line in lines[1:]] == list(flatten(cfg))
    assert "--model.num_layers=3" in lines and "--cache.enabled=false" in lines
    # Pasting the printed lines back gives the same config (but for the two keys the CLI cannot set).
    settable = [line for line in format_config(cfg).splitlines()[1:]
                if line.split("=", 1)[0] not in ("--augment.seg_classes", "--mesh.rules")]
    assert apply_overrides(configs.get("sword:paper"), settable) == cfg
