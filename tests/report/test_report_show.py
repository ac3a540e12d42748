"""`show` renders a results or sweep file and refuses anything else clearly."""

import pytest
import yaml

from oodrl.errors import StoreError
from oodrl.report.show import load_report, show
from oodrl.report.tables import render_tables, sweep_tables


def write(path, data):
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def test_show_results_file(results, tmp_path):
    path = write(tmp_path / "results.yaml", results)
    assert load_report(path)[0] == "results"
    text = show(path)
    assert text == render_tables(results)
    assert "## Null baseline" in text


def test_show_sweep_file(sweep, tmp_path):
    path = write(tmp_path / "sweep_results.yaml", sweep)
    assert load_report(path)[0] == "sweep"
    assert show(path) == sweep_tables(sweep)
    assert "σ=0.8" in show(path)


def test_show_refuses_missing_and_foreign_files(tmp_path):
    with pytest.raises(StoreError, match="No report file"):
        show(tmp_path / "nothing.yaml")
    with pytest.raises(StoreError, match="neither a results file"):
        show(write(tmp_path / "params.yaml", {"seed": 0}))
    with pytest.raises(StoreError, match="not a YAML"):
        (tmp_path / "bad.yaml").write_text("a: [unclosed", encoding="utf-8")
        show(tmp_path / "bad.yaml")
    with pytest.raises(StoreError, match="Record 0"):
        show(write(tmp_path / "r.yaml", {"records": [{"detector": "a"}]}))
    with pytest.raises(StoreError, match="not a YAML"):
        (tmp_path / "binary.yaml").write_bytes(b"\xff\xfe\x00")
        show(tmp_path / "binary.yaml")


# -- run_meta.yaml: each detector's cost beside its accuracy (SPEC §13) -------------------------
COST = {
    "cusum": {"fit_s": 0.2, "fitted_bytes": 2048, "step_us_median": 40.0, "step_us_p99": 80.0},
    "mahalanobis_distance": {
        "fit_s": 0.25, "fitted_bytes": 1536, "step_us_median": 30.0, "step_us_p99": 60.0,
    },
    "kde_density": {
        "fit_s": None, "fitted_bytes": 262144, "step_us_median": 250.0, "step_us_p99": 500.0,
    },
}  # fmt: skip


def _rows(output: str) -> list[list[str]]:
    lines = [line for line in output.splitlines() if line.startswith("| ")][2:]
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]


def test_show_run_meta_puts_cost_beside_accuracy(results, tmp_path):
    from typer.testing import CliRunner

    from oodrl.cli import app
    from oodrl.report.tables import anomaly_records, detector_means

    write(tmp_path / "results.yaml", results)
    path = write(tmp_path / "run_meta.yaml", {"oodrl_version": "0", "cost": COST})
    aurocs = detector_means(anomaly_records(results), "matched_auroc")
    runner = CliRunner()

    shown = runner.invoke(app, ["show", str(path)])
    assert shown.exit_code == 0, shown.output
    rows = _rows(shown.output)
    assert [r[0] for r in rows] == sorted(COST, key=lambda d: -aurocs[d])  # most accurate first
    kde = next(r for r in rows if r[0] == "kde_density")
    assert kde == ["kde_density", f"{aurocs['kde_density']:.3f}", "—", "256.0", "250.0", "500.0"]

    fast = runner.invoke(app, ["show", str(path), "--max-us-per-step", "50"])
    assert fast.exit_code == 0, fast.output
    assert {r[0] for r in _rows(fast.output)} == {"cusum", "mahalanobis_distance"}
    best = max(["cusum", "mahalanobis_distance"], key=aurocs.get)
    assert f"Most accurate at ≤ 50 µs/step (median): {best} (matched AUROC " in fast.output

    none = runner.invoke(app, ["show", str(path), "--max-us-per-step", "10"])
    assert "No detector streams at ≤ 10 µs/step (median)." in none.output

    refused = runner.invoke(app, ["show", str(tmp_path / "results.yaml"), "--max-us-per-step", "5"])
    assert refused.exit_code == 2 and "Pass reports/run_meta.yaml" in refused.output


def test_show_run_meta_without_results_beside_it(tmp_path):
    path = write(tmp_path / "run_meta.yaml", {"cost": COST})
    assert load_report(path)[0] == "meta"
    assert {r[1] for r in _rows(show(path))} == {"—"}
    assert "not ranked" in show(path, max_us_per_step=50)
