"""The paper experiments (experiments/run_all.py and its scripts) cannot rot.

One test runs ``run_all.py --quick`` into a temporary folder and checks that every table and
figure exists and holds numbers; the others check the experiments' building blocks against
independent arithmetic (the soil model, the paper's tables, the terrain design, the statistics).
"""

from __future__ import annotations

import importlib
import math
import re
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = ROOT / "experiments"
OUTPUTS = {
    "paper_terrain.md": ["paper_terrain.png"],
    "paper_precision.md": ["paper_precision.png"],
    "paper_depth.md": ["paper_depth.png"],
    "exp_lighting.md": ["exp_lighting.png"],
    "exp_uncertainty.md": ["exp_uncertainty_reliability.png", "exp_uncertainty_sigma.png"],
    "exp_calibration.md": ["exp_calibration.png"],
    "exp_speed.md": ["exp_speed.png"],
}
NUMBER = re.compile(r"-?\d+\.\d+|-?\d+")


def _module(name: str) -> ModuleType:
    if str(EXPERIMENTS) not in sys.path:
        sys.path.insert(0, str(EXPERIMENTS))
    return importlib.import_module(name)


def _table_rows(text: str) -> list[list[str]]:
    """Body rows of every Markdown table in ``text``."""
    rows = []
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("|") and i > 0 and lines[i - 1].startswith("|"):
            if set(line.replace("|", "").strip()) <= {"-", ":"}:
                continue
            rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows


@pytest.mark.heavy
@pytest.mark.slow
def test_run_all_quick_writes_every_table_and_figure(tmp_path: Path) -> None:
    out, cache = tmp_path / "results", tmp_path / "cache"
    # One worker process (--jobs 1): pytest's own workers already keep the cores busy, and one
    # process compiles the soft method once where two compile it twice.
    cmd = [sys.executable, str(EXPERIMENTS / "run_all.py"), "--quick", "--jobs", "1"]
    cmd += ["--out-dir", str(out)]
    proc = subprocess.run(
        [*cmd, "--cache-dir", str(cache)],
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-6000:]
    for md, pngs in OUTPUTS.items():
        text = (out / md).read_text(encoding="utf-8")
        rows = _table_rows(text)
        assert rows, f"{md} has no table"
        numbers = [float(x) for r in rows for c in r[1:] for x in NUMBER.findall(c)]
        assert numbers and all(math.isfinite(x) for x in numbers), md
        for png in pngs:
            data = (out / png).read_bytes()
            assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, png
            assert f"]({png})" in text, f"{md} does not show {png}"
    index = (out / "README.md").read_text(encoding="utf-8")
    for name in (*OUTPUTS, *(p for ps in OUTPUTS.values() for p in ps)):
        assert f"]({name})" in index, f"the index does not link {name}"
    headline = _table_rows(index.split("## Headline")[1].split("##")[0])
    assert len(headline) >= 10
    # classic and soft columns hold a measurement in every row the method has one for.
    for row in headline:
        for cell in row[2:4]:
            assert NUMBER.search(cell) or cell in ("—", "no uncertainty"), row
    assert "FAILED" not in proc.stderr
    # Every compute experiment left its per-frame records for the uncertainty pooling.
    for name in ("paper_terrain", "paper_precision", "paper_depth", "exp_lighting"):
        assert (cache / f"{name}_frames.csv").is_file()


def test_paper_tables_copied_from_the_paper() -> None:
    c = _module("common.paper")
    assert c.PAPER_SLIPS == (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)
    for load in (30, 90):
        for q in ("sinkage", "theta1", "theta2"):
            assert len(c.PAPER_TABLES[load][q]) == 8
    # Spot checks against the paper's text: first and last cells of each table.
    assert c.PAPER_TABLES[30]["sinkage"][-1] == 8.70
    assert c.PAPER_TABLES[30]["theta1"][0] == 19.74
    assert c.PAPER_TABLES[90]["sinkage"][6] == 9.13
    assert c.PAPER_TABLES[90]["theta2"][-1] == 3.82


def test_soil_model_matches_bekker_by_hand() -> None:
    c = _module("common.paper")
    # Bekker by hand, 90 N, Table 1 soil, b = 0.15 m, D = 0.28 m.
    k = -20.7e3 / 0.15 + 1594.8e3
    z = (3 * 90 / ((3 - 0.79) * 0.15 * k * math.sqrt(0.28))) ** (2 / 2.58)
    assert c.bekker_static_sinkage_mm(90.0) == pytest.approx(1000 * z * c.LUG_SINKAGE_FACTOR)
    assert 3.0 < c.sinkage_for(30, 0.0) < c.sinkage_for(30, 0.7) < c.sinkage_for(90, 0.7)
    assert c.slip_sinkage_factor(0.0) == 1.0
    assert c.slip_sinkage_factor(0.6) == pytest.approx(1.6 / 0.7)


def test_terrain_design_orders_true_sinkage_as_the_paper_says(tmp_path: Path) -> None:
    """Raised terrain: true sinkage > the flat-level sensor value; hollow, rough: less."""
    from sinkjax import synth as S

    c = _module("common.scenery")
    terrain = _module("paper_terrain")
    setup = _module("common.runs").make_setup(True, tmp_path / "o", tmp_path / "c")
    base = c.paper_scene(setup)
    for name, sign in terrain.EXPECTED.items():
        for slip in terrain.SLIPS:
            scene, sensor = terrain.terrain_scene(base, name, slip, np.random.default_rng(0))
            true = S.true_geometry(scene).sinkage_mm
            assert c.valid_contact(scene)
            if sign:
                assert np.sign(true - sensor) == sign, (name, slip, true, sensor)
            else:
                assert abs(true - sensor) < 0.15 * sensor, (name, slip, true, sensor)


def test_every_experiment_scene_has_one_rig(tmp_path: Path) -> None:
    """Terrain and lighting change nothing the rig depends on: one compile per image size."""
    from sinkjax import synth as S

    c = _module("common.scenery")
    lighting = _module("exp_lighting")
    setup = _module("common.runs").make_setup(False, tmp_path / "o", tmp_path / "c")
    base = c.paper_scene(setup)
    scenes = [c.place(base, d, **c.bulldozing(base, d, 0.5)) for d in (1.0, 20.0)]
    for factor, (_, levels, _) in lighting.FACTORS.items():
        scenes += [lighting.condition(base, factor, lv) for lv in levels]
    rigs = [S.rig_for(s) for s in scenes]
    assert len({(r.confidence_rect, r.travel, r.wheel_radius_mm) for r in rigs}) == 1


def test_coverage_statistics() -> None:
    u = _module("exp_uncertainty")
    # The interval half-width in reported sigmas: the Student-t quantile over its standard
    # deviation for the shipped model's degrees of freedom (scipy as the reference), times the
    # model's level correction interpolated at p (numpy's interp).
    from scipy import stats

    from sinkjax import UncertaintyModel
    from sinkjax.soft.uncertainty import ADJUST_LEVELS

    model = UncertaintyModel()
    dofs = [float(d) for d in model.dofs()]

    def want_k(p: float, i: int = 0) -> float:
        adjust = np.interp(p, ADJUST_LEVELS, model.level_adjust[i])
        return float(stats.t.ppf(0.5 + p / 2, dofs[i]) / stats.t.std(dofs[i]) * adjust)

    for i, q in enumerate(("sinkage", "theta1", "theta2")):
        for p in (0.5, 0.8, 0.95):
            assert u.z_for(p, q) == pytest.approx(want_k(p, i), rel=1e-4)
    lo, hi = u.wilson(45, 50)
    assert lo < 0.9 < hi and 0 <= lo and hi <= 1
    # Wilson by hand for 8 of 10 at z = 1.96: centre (0.8 + 0.19208) / 1.38416.
    lo, hi = u.wilson(8, 10)
    half = 1.96 * math.sqrt(0.8 * 0.2 / 10 + 1.96**2 / 400) / (1 + 1.96**2 / 10)
    assert (lo + hi) / 2 == pytest.approx((0.8 + 1.96**2 / 20) / (1 + 1.96**2 / 10))
    assert (hi - lo) / 2 == pytest.approx(half)
    # Coverage of records by the rule of sinkjax.metrics: only soft-ok frames with a sigma.
    # Errors of 1.1 and 0.9 times the 50 % half-width (checked against scipy above), both well
    # inside the 95 % one.
    k50, k95 = (want_k(p) for p in (0.5, 0.95))
    assert 1.1 * k50 < 0.9 * k95
    recs = [
        {"true_sinkage": 10.0, "soft_status": "ok", "soft_sinkage": 10.0 + 1.1 * k50 * 0.3},
        {"true_sinkage": 10.0, "soft_status": "ok", "soft_sinkage": 10.0 - 0.9 * k50 * 0.3},
        {"true_sinkage": 5.0, "soft_status": "fit_failed", "soft_sinkage": math.nan},
    ]
    for r, std in zip(recs, (0.3, 0.3, math.nan), strict=True):
        r["soft_sinkage_std"] = std
    hits = u.covered(recs, "sinkage", 0.95)
    assert hits[:2].tolist() == [1.0, 1.0] and math.isnan(hits[2])
    hits = u.covered(recs, "sinkage", 0.5)
    assert hits[:2].tolist() == [0.0, 1.0]


def test_reports_are_made_from_saved_numbers(tmp_path: Path) -> None:
    """bench.py and benchmark.py write their Markdown from the JSON they save, which the
    readers (exp_speed) use instead of parsing Markdown."""
    bench = _module("bench")
    data = {
        "quick": True,
        "seconds": 12.0,
        "date": "2026-01-01 00:00",
        "machine": "test machine",
        "load_average": [1.0, 2.0, 3.0],
        "cpu_count": 2,
        "rows": [
            {"method": "classic", "size": "640x480", "batch": 1, "frames": 4, "compile_s": 0.0}
            | {"seconds": 2.0, "fps": 2.0, "peak_mib": 300.0, "statuses": {"ok": 4}},
            {"method": "soft", "size": "640x480", "batch": 8, "frames": 8, "compile_s": 5.0}
            | {"seconds": 1.0, "fps": 8.0, "peak_mib": 800.0, "statuses": {"ok": 8}},
        ],
    }
    text = bench.report(data)
    assert "| soft | 640x480 | 8 | 8 | 5.0 | 8.00 | 125 | 800 |" in text
    assert "soft is 4.0x classic" in text
    # A GPU run's report: the compiled method's rates, statuses and z0 errors per row.
    gpu_rows = [
        data["rows"][0] | {"z0_mm": [1.0, None], "true_z0_mm": [1.25, 2.0]},
        data["rows"][1]
        | {"statuses": {"ok": 6, "fit_failed": 2}, "device_fps": 500.0, "transfer_fps": 400.0}
        | {"z0_mm": [3.0], "true_z0_mm": [2.5]},
    ]
    gpu = bench.report(data | {"backend": "gpu", "rows": gpu_rows})
    assert "## GPU numbers" in gpu and "## CPU numbers" not in gpu
    assert "| classic | 640x480 | 1 | - | 2.0 | - | - | - | 0 | -0.250, failed |" in gpu
    soft_row = "| soft | 640x480 | 8 | 5.0 | 8.0 | 400 | 500 | 2.00 | 2 of 8 fit_failed | +0.500 |"
    assert soft_row in gpu
    assert "soft is 250.0x classic" in gpu
    benchmark = _module("benchmark")
    cols = [
        {
            "name": "soft",
            "seconds_per_frame": 0.05,
            "metrics": dict.fromkeys((key for _, key, _ in benchmark.ROWS), 1.0)
            | {"failed_pct": None},
        },
    ]
    table = benchmark.table(cols)
    assert "| failed frames (%) | — | <= 2 |" in table
    assert "| time per frame, steady state (ms) | 50.0 |" in table
    speed = _module("exp_speed")
    runs = _module("common.runs")
    setup = runs.make_setup(True, tmp_path / "out", tmp_path / "cache")
    (setup.out_dir / "bench.json").write_text(__import__("json").dumps(data), encoding="utf-8")
    summary = speed.run(setup)
    assert summary["640x480_classic_fps"] == 2.0 and summary["640x480_soft_fps"] == 8.0
    assert summary["640x480_soft_batch"] == "8"
