"""Tests for mbst.report.summary.write_summary: results/summary.csv from per-campaign results."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from mbst.report.summary import COLUMNS, write_summary

CORR_HEADER = "test,channel,fit_percent,nrmse,pearson_r,r2,max_abs_error\n"


def make_result(root: Path, campaign: str, rows: list[tuple[str, str, float]]) -> Path:
    d = root / campaign
    (d / "identify").mkdir(parents=True)
    lines = [f"{t},{c},{f},0.1,0.99,0.98,0.5\n" for t, c, f in rows]
    (d / "identify" / "correlation.csv").write_text(CORR_HEADER + "".join(lines))
    return d


def read(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def test_base_rows_from_identify(tmp_path):
    a = make_result(tmp_path, "demo-eps", [("s2_ctrl", "steering_torque_nm", 81.25),
                                          ("s2_ctrl", "rack_position_m", 90.0)])
    b = make_result(tmp_path, "my-rig", [("t9", "steering_torque_nm", -12.5)])
    out = write_summary([a, b], tmp_path / "out" / "summary.csv")
    assert out == tmp_path / "out" / "summary.csv"
    assert out.read_text().splitlines()[0] == ",".join(COLUMNS)
    rows = read(out)
    assert [(r["campaign"], r["test"], r["channel"], r["model"]) for r in rows] == [
        ("demo-eps", "s2_ctrl", "steering_torque_nm", "base"),
        ("demo-eps", "s2_ctrl", "rack_position_m", "base"),
        ("my-rig", "t9", "steering_torque_nm", "base"),
    ]
    assert [float(r["fit_percent"]) for r in rows] == [81.25, 90.0, -12.5]


def test_discovery_adds_extended_rows(tmp_path):
    a = make_result(tmp_path, "demo-eps", [("s2_ctrl", "steering_torque_nm", 70.0)])
    (a / "discover").mkdir()
    (a / "discover" / "discovery.json").write_text(json.dumps({
        "format": "mbst-discovery/1", "campaign": "demo-eps",
        "base": {"params": {}, "control_fit_percent": {"s2_ctrl": {"steering_torque_nm": 70.0}}},
        "findings": [],
        "extended": {"params": {},
                     "control_fit_percent": {"s2_ctrl": {"steering_torque_nm": 88.5}}},
    }))
    rows = read(write_summary([a], tmp_path / "summary.csv"))
    assert [(r["model"], float(r["fit_percent"])) for r in rows] == [
        ("base", 70.0), ("extended", 88.5)]


def test_missing_correlation_names_folder_and_writes_nothing(tmp_path):
    a = make_result(tmp_path, "demo-eps", [("s2", "steering_torque_nm", 1.0)])
    missing = tmp_path / "my-rig"
    missing.mkdir()
    out = tmp_path / "summary.csv"
    with pytest.raises(FileNotFoundError, match="my-rig"):
        write_summary([a, missing], out)
    assert not out.exists()
    assert list(tmp_path.glob(".summary.csv.*")) == []


def test_bad_table_is_an_error(tmp_path):
    d = tmp_path / "c" / "identify"
    d.mkdir(parents=True)
    (d / "correlation.csv").write_text("test,channel\ns1,steering_torque_nm\n")
    with pytest.raises(ValueError, match="fit_percent"):
        write_summary([tmp_path / "c"], tmp_path / "s.csv")
    (d / "correlation.csv").write_text("test,channel,fit_percent\ns1,x,abc\n")
    with pytest.raises(ValueError, match="line 2"):
        write_summary([tmp_path / "c"], tmp_path / "s.csv")


def test_overwrite_is_atomic_replace(tmp_path):
    a = make_result(tmp_path, "demo-eps", [("s2", "steering_torque_nm", 1.0)])
    out = tmp_path / "summary.csv"
    out.write_text("old\n")
    write_summary([a], out)
    assert read(out)[0]["campaign"] == "demo-eps"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    assert out.stat().st_mode & 0o644 == 0o644


def test_no_dirs_is_an_error(tmp_path):
    with pytest.raises(ValueError):
        write_summary([], tmp_path / "s.csv")


def test_discovery_without_extended_or_malformed(tmp_path):
    a = make_result(tmp_path, "demo-eps", [("s2", "steering_torque_nm", 1.0)])
    (a / "discover").mkdir()
    disc = a / "discover" / "discovery.json"
    disc.write_text(json.dumps({"format": "mbst-discovery/1", "findings": []}))
    assert [r["model"] for r in read(write_summary([a], tmp_path / "s.csv"))] == ["base"]
    disc.write_text(json.dumps({"extended": {"control_fit_percent": {"s2": 5}}}))
    with pytest.raises(ValueError, match="discovery.json"):
        write_summary([a], tmp_path / "s.csv")
    disc.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        write_summary([a], tmp_path / "s.csv")
