"""The benchmarks' command lines answer a bad argument as the entry points do: one line on stderr,
a non-zero exit status, no traceback (``sword_jax.cli.run``)."""

import ast
import glob
import os
import subprocess
import sys

import pytest

from tests.conftest import REPO, example_env


@pytest.mark.parametrize("argv,expected", [
    # a config conflict, found by the config's validation
    (["benchmarks.bench_policy", "grpo", "--config", "sword:tiny", "--out", "{tmp}", "--rl.grpo.group_size=1"],
     "rl.grpo.group_size must be >= 2"),
    # a flat key of earlier versions, refused naming the new one
    (["benchmarks.bench_policy", "grpo", "--config", "sword:tiny", "--out", "{tmp}", "--rl.sft_steps=3"],
     "rl.sft_steps is now rl.sft.steps"),
    (["benchmarks.bench_policy", "eval", "--config", "sword:tiny", "--out", "{tmp}", "--policy", "{tmp}/none.npz"],
     "no such file"),
    (["benchmarks.bench_dlb", "--tiny", "--model.no_such_key=3"], "unknown config key 'model.no_such_key'"),
    (["benchmarks.bench_vae", "--iters", "many"], "argument --iters: invalid int value"),
    (["benchmarks.bench_brax_ppo", "--envs", "mjx,gym"], "unknown env(s) ['gym']"),
    (["benchmarks.bench_brax_ppo", "--iterations", "1"], "--iterations must be at least 2"),
    (["benchmarks.bench_multiprocess", "--processes", "1", "--cpu-devices", "2"], "--processes must be >= 2"),
    (["benchmarks.bench_multiprocess", "--processes", "2", "--cpu-devices", "2", "--data.batch_size=6"],
     "must be multiples of the 4 devices"),
])
def test_a_bad_argument_is_one_line_without_a_traceback(argv, expected, tmp_path):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    proc = subprocess.run([sys.executable, "-m", *argv], cwd=REPO, env=example_env(), capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{argv[0]}: error: ") and expected in lines[0], proc.stderr


def _runs_main_through_cli(path: str) -> bool:
    """Whether the module's ``if __name__ == "__main__":`` block is ``cli.run(main)``."""
    tree = ast.parse(open(path).read())
    for node in tree.body:
        if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test):
            return [ast.unparse(stmt) for stmt in node.body] == ["cli.run(main)"]
    return True  # not a command


def test_every_benchmark_command_runs_through_the_shared_error_handling():
    paths = sorted(glob.glob(os.path.join(REPO, "benchmarks", "*.py")))
    commands = [p for p in paths if "__main__" in open(p).read()]
    assert len(commands) >= 15
    assert [os.path.basename(p) for p in commands if not _runs_main_through_cli(p)] == []
    # their parsers raise UsageError (one line) rather than argparse's usage text
    assert [os.path.basename(p) for p in commands if "argparse.ArgumentParser(" in open(p).read()] == []
