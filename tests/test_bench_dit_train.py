"""bench_dit_train's sweep of world-model sizes at small's geometry, on CPU smoke shapes."""

import pytest

from benchmarks import bench_dit_train


def test_the_small_sweep_times_each_size_beside_the_first_and_refuses_bad_sizes(capsys):
    rows = bench_dit_train.main(["--tiny", "--small-sweep", "64x1,128x2", "--skip-wide", "--no-record"])
    assert [r["config"] for r in rows] == ["small-64x1", "small-128x2"]
    first, second = rows
    assert first["params_vs_first"] == 1.0 and first["step_vs_first"] == 1.0
    assert second["params"] > 2 * first["params"] and second["params_vs_first"] == second["params"] / first["params"]
    assert second["s_per_small_run"] == pytest.approx(second["dlb_step_s"] * bench_dit_train.SMALL_STEPS)
    assert all(r["dlb_step_s"] > 0 and r["layers"] == layers for r, layers in zip(rows, (1, 2)))
    assert "small-128x2" in capsys.readouterr().out
    for bad in ("64", "100x2", "64x0", "ax2"):
        with pytest.raises(SystemExit, match="--small-sweep takes DIMxLAYERS"):
            bench_dit_train.main(["--tiny", "--small-sweep", bad, "--skip-wide", "--no-record"])
    with pytest.raises(SystemExit, match="--skip-wide leaves rows only with --small-sweep"):
        bench_dit_train.main(["--tiny", "--skip-wide"])
