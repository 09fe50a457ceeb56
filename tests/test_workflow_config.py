"""The workflow's config: every shipped config validates against the schema, and an
import's `control:` reaches `mbst import` (a set of the friction damper without
earthquake runs runs through the pipeline, not only through the CLI)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import jsonschema
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())


WORKFLOW_CONFIGS = sorted(p.name for p in (ROOT / "config").glob("*.yaml")
                          if "campaigns" in yaml.safe_load(p.read_text()))  # not plan.yaml


@pytest.mark.parametrize("name", WORKFLOW_CONFIGS)
def test_shipped_configs_validate(name):
    jsonschema.validate(yaml.safe_load((ROOT / "config" / name).read_text()), SCHEMA)


def _with_control(control: str | None) -> dict:
    doc = yaml.safe_load((ROOT / "config/friction-damper.yaml").read_text())
    entry = doc["campaigns"]["friction-damper"]["import"]
    if control is not None:
        entry["control"] = control
    return doc


def test_import_control_validates_and_a_typo_does_not():
    jsonschema.validate(_with_control("1Hz*"), SCHEMA)
    bad = _with_control(None)
    bad["campaigns"]["friction-damper"]["import"]["controls"] = "1Hz*"
    with pytest.raises(jsonschema.ValidationError, match="controls"):
        jsonschema.validate(bad, SCHEMA)


@pytest.mark.skipif(shutil.which("snakemake") is None, reason="snakemake not on PATH")
def test_import_control_reaches_the_import_command(tmp_path):
    cfg = tmp_path / "fd.yaml"
    cfg.write_text(yaml.safe_dump(_with_control("1Hz*")))
    out = subprocess.run(
        ["snakemake", "-n", "-p", "--configfile", str(cfg), "--replace-workflow-config",
         "results/friction-damper/import/campaign"],
        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr + out.stdout
    line = next(ln for ln in (out.stdout + out.stderr).splitlines() if "mbst import" in ln)
    assert "--control '1Hz*'" in line
