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
