"""Read, validate and write test campaigns (``mbst-campaign/1``).

The format is specified in ``campaign-format.md``: a directory holding a
``campaign.yaml`` and one CSV or Parquet file per test. Everything about the
rig (scenarios, channel names, which channels are required, motor modes) is
asked from the system family named by the campaign's ``system:`` key, so this
module knows no channel names of its own.

Every problem found while reading is raised as a :class:`CampaignError` whose
message is one line naming the campaign, the test, the file, the column and
the row where they are known. Rows are counted 1-based over *data* rows: row 1
is the first line after the CSV header (the first row of a Parquet table).
"""

from __future__ import annotations

import csv
import math
import os
import re
import shutil
import uuid
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import yaml

from mbst.core.family import SystemFamily, get_system, known_systems
from mbst.core.filtering import signal_resolution

if TYPE_CHECKING:
    from mbst.core.model import ModelDefinition

FORMAT = "mbst-campaign/1"
CAMPAIGN_FILE = "campaign.yaml"
ROLES = ("identification", "control")
DATA_EXTENSIONS = (".csv", ".parquet")
MIN_SAMPLES = 100
TIME_UNIFORMITY = 0.01  # every dt within 1 % of the median dt

_TOP_KEYS = ("format", "name", "system", "known", "tests")
_TEST_KEYS = (
    "id",
    "file",
    "scenario",
    "input",
    "motor",
    "role",
    "vehicle_speed_kph",
    "assist_mode",
)
_REQUIRED_TEST_KEYS = ("id", "file", "scenario", "input", "motor", "role")

__all__ = [
    "Campaign",
    "CampaignError",
    "TestSpec",
    "read_campaign",
    "summarize_campaign",
    "write_campaign",
]


class CampaignError(Exception):
    """A problem with a campaign, reported as one user-facing line.

    Parameters
    ----------
    message
        What is wrong, without the location.
    campaign, test, column
        Campaign name, test id and column name, where known.
    row
        1-based data row (row 1 is the first line after the CSV header).
    path
        The file concerned (``campaign.yaml`` or a test file).

    Notes
    -----
    ``str(err)`` joins every known piece, e.g. ``campaign 'demo-eps', test
    's2_sine', file tests/s2_sine.csv, column 'steering_torque_nm', row 17:
    value is NaN``.
    """

    def __init__(
        self,
        message: str,
        *,
        campaign: str | None = None,
        test: str | None = None,
        column: str | None = None,
        row: int | None = None,
        path: str | Path | None = None,
    ) -> None:
        # Newlines (e.g. from yaml's messages) would break the one-line promise.
        self.message = " ".join(str(message).split())
        self.campaign = campaign
        self.test = test
        self.column = column
        self.row = row
        self.path = path
        super().__init__(self.message)

    def __str__(self) -> str:
        parts = []
        if self.campaign is not None:
            parts.append(f"campaign '{self.campaign}'")
        if self.test is not None:
            parts.append(f"test '{self.test}'")
        if self.path is not None:
            parts.append(f"file {self.path}")
        if self.column is not None:
            parts.append(f"column '{self.column}'")
        if self.row is not None:
            parts.append(f"row {self.row}")
        where = ", ".join(parts)
        return f"{where}: {self.message}" if where else self.message

    def __reduce__(self):
        # Keep the keyword attributes when pickled across processes.
        kwargs = {
            "campaign": self.campaign,
            "test": self.test,
            "column": self.column,
            "row": self.row,
            "path": self.path,
        }
        return (_rebuild_error, (self.message, kwargs))


def _rebuild_error(message: str, kwargs: dict) -> CampaignError:
    return CampaignError(message, **kwargs)


@dataclass
class TestSpec:
    """One entry of ``tests:`` in ``campaign.yaml``.

    ``file`` is relative to the campaign directory. Unknown keys of the entry
    are kept in ``extra`` and written back unchanged.
    """

    id: str
    file: str
    scenario: str
    input: dict
    motor: str
    role: str
    vehicle_speed_kph: float | None = None
    assist_mode: str | None = None
    extra: dict = field(default_factory=dict)
    __test__ = False  # keep pytest from collecting it

    @property
    def input_kind(self) -> str | None:
        """The profile kind (``sine``, ``sweep``, ...) or ``None`` if not given."""
        kind = self.input.get("kind")
        return None if kind is None else str(kind)


@dataclass
class Campaign:
    """A validated campaign.

    Attributes
    ----------
    path
        The campaign directory (the one holding ``campaign.yaml``).
    name, system
        From ``campaign.yaml``; ``system`` names a registered system family.
    known
        A-priori parameter values (SI units), as floats: fixed values and the
        centres of priors alike.
    priors
        Name -> standard deviation (SI units) of the ``known`` values given as
        a prior ``{value, sigma}``: fitted with a Gaussian prior term instead
        of held fixed.
    tests
        Test entries in file order.
    extra
        Unknown top-level keys, passed through.
    data
        Test id -> validated frame; filled by :func:`read_campaign` or lazily
        by :meth:`frame`. Known channels are ``float64``; extra columns are kept
        as read.
    """

    path: Path
    name: str
    system: str
    known: dict[str, float]
    tests: list[TestSpec]
    extra: dict = field(default_factory=dict)
    priors: dict[str, float] = field(default_factory=dict)
    data: dict[str, pd.DataFrame] = field(default_factory=dict, repr=False, compare=False)
    _model: Any = field(default=None, init=False, repr=False, compare=False)

    def model(self) -> ModelDefinition:
        """The family's model definition with this campaign's own parameters (cached).

        Every prepared test of a campaign shares this one object, so a fit
        and its parameter vectors agree on the layout.
        """
        if self._model is None:
            self._model = self.family.model().for_campaign(self)
        return self._model

    @property
    def family(self) -> SystemFamily:
        """The system family named by ``system``."""
        return get_system(self.system)

    def test(self, test_id: str) -> TestSpec:
        """Return the test called ``test_id``; :class:`CampaignError` if there is none."""
        for spec in self.tests:
            if spec.id == test_id:
                return spec
        ids = ", ".join(s.id for s in self.tests)
        raise CampaignError(
            f"no such test; the campaign has: {ids}", campaign=self.name, test=test_id
        )

    def identification_tests(self) -> list[TestSpec]:
        """Tests with ``role: identification`` (the only ones a fit may use)."""
        return [s for s in self.tests if s.role == "identification"]

    def control_tests(self) -> list[TestSpec]:
        """Tests with ``role: control`` (held out, correlation only)."""
        return [s for s in self.tests if s.role == "control"]

    def file_path(self, test_id: str) -> Path:
        """Absolute location of the data file of ``test_id``."""
        return self.path / self.test(test_id).file

    def frame(self, test_id: str) -> pd.DataFrame:
        """Validated data of ``test_id``, read and checked on first use.

        Raises
        ------
        CampaignError
            If the test is unknown or its file fails validation.
        """
        if test_id not in self.data:
            spec = self.test(test_id)
            self.data[test_id] = _load_test_data(
                self.path / spec.file, spec, self.family, self.name
            )
        return self.data[test_id]

    def sample_time_s(self, test_id: str) -> float:
        """Median sample time of ``test_id`` in seconds."""
        t = self.frame(test_id)[self.family.time_channel].to_numpy(dtype=float)
        return float(np.median(np.diff(t)))


# --------------------------------------------------------------------------- reading


def running_order_places(ids: list[str]) -> dict[str, float]:
    """Places of tests run in the order ``ids``, −½ (first) … ½ (last); one step more is
    the place of a test run after them (``places_step``). Where a rig that drifts over
    the campaign stands (``ModelDefinition.campaign_drift``)."""
    return {tid: i * places_step(ids) - 0.5 for i, tid in enumerate(ids)}


def places_step(ids: list[str]) -> float:
    """The distance between two neighbours in ``running_order_places``."""
    return 1.0 / max(len(ids) - 1, 1)


def read_campaign(path: str | Path, load_data: bool = True) -> Campaign:
    """Read and validate a campaign.

    Parameters
    ----------
    path
        The campaign directory or its ``campaign.yaml``.
    load_data
        If true, read and validate every test file now and keep the frames in
        ``Campaign.data``; otherwise only check ``campaign.yaml`` and that each
        file exists, and load frames on first :meth:`Campaign.frame`.

    Returns
    -------
    Campaign

    Raises
    ------
    CampaignError
        At the first problem. Rows in messages are 1-based data rows: row 1 is
        the first line after the CSV header.
    """
    yaml_path = _locate_yaml(Path(path))
    doc = _load_yaml(yaml_path)
    campaign = _parse_campaign(doc, yaml_path)
    if load_data:
        for spec in campaign.tests:
            campaign.frame(spec.id)
    return campaign


def _locate_yaml(path: Path) -> Path:
    if path.is_dir():
        yaml_path = path / CAMPAIGN_FILE
        if not yaml_path.is_file():
            raise CampaignError(f"missing {CAMPAIGN_FILE} in campaign directory", path=path)
        return yaml_path
    if path.is_file():
        return path
    raise CampaignError("no such campaign directory or campaign.yaml", path=path)


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a key written twice in one mapping (PyYAML keeps the
    last silently: a test's `role` given twice would end as whichever came second)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: set = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, (str, int, float, bool)) and key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key '{key}' is given twice in one mapping", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def _load_yaml(yaml_path: Path) -> Any:
    try:
        text = yaml_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise CampaignError(f"cannot read: {exc}", path=yaml_path) from exc
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a safe loader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or str(exc)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise CampaignError(f"YAML does not parse{where}: {problem}", path=yaml_path) from exc


def _parse_campaign(doc: Any, yaml_path: Path) -> Campaign:
    """Check a parsed ``campaign.yaml`` top to bottom and build the :class:`Campaign`."""
    if not isinstance(doc, dict):
        got = "an empty file" if doc is None else type(doc).__name__
        raise CampaignError(f"top level must be a mapping, got {got}", path=yaml_path)

    # Name the campaign in errors as early as possible, even before `format` is checked.
    raw_name = doc.get("name")
    label = str(raw_name) if _is_scalar(raw_name) else None

    def fail(message: str, test: str | None = None) -> CampaignError:
        return CampaignError(message, campaign=label, test=test, path=yaml_path)

    name = _campaign_name(doc, fail)
    system = _campaign_system(doc, fail)
    family = get_system(system)

    known, priors = _parse_known(doc.get("known"), fail)
    _check_known_ranges(known, family, fail)
    tests = _parse_tests(doc["tests"], yaml_path.parent, family, name, fail)

    _check_controls_held_out(tests, yaml_path.parent, name)
    extra = {k: v for k, v in doc.items() if k not in _TOP_KEYS}
    return Campaign(
        path=yaml_path.parent,
        name=name,
        system=system,
        known=known,
        tests=tests,
        extra=extra,
        priors=priors,
    )


def _campaign_name(doc: dict, fail: Callable[..., CampaignError]) -> str:
    """The campaign's name, after the ``format`` and the required top-level keys."""
    if "format" not in doc:
        raise fail(f"missing key 'format' (expected '{FORMAT}')")
    if doc["format"] != FORMAT:
        raise fail(f"format is {doc['format']!r}, expected '{FORMAT}'")
    for key in ("name", "system", "tests"):
        if key not in doc or doc[key] is None:
            raise fail(f"missing key '{key}'")
    raw_name = doc["name"]
    if not _is_scalar(raw_name) or str(raw_name).strip() == "":
        raise fail("'name' must be a non-empty string")
    return str(raw_name)


def _campaign_system(doc: dict, fail: Callable[..., CampaignError]) -> str:
    """The ``system:`` key, which must name a registered system family."""
    system = doc["system"]
    systems = known_systems()
    if not isinstance(system, str) or system not in systems:
        raise fail(f"unknown system {system!r}; known systems: {', '.join(systems)}")
    return system


def _parse_tests(raw_tests: Any, root: Path, family: SystemFamily, campaign: str,
                 fail: Callable[..., CampaignError]) -> list[TestSpec]:
    """``tests:`` as specs in file order: ids unique and usable as file names, each data
    file (relative to the campaign directory ``root``) of a known type and present."""
    if not isinstance(raw_tests, list):
        raise fail(f"'tests' must be a list, got {type(raw_tests).__name__}")
    if not raw_tests:
        raise fail("'tests' is empty; a campaign needs at least one test")

    tests: list[TestSpec] = []
    seen: set[str] = set()
    for index, entry in enumerate(raw_tests):
        spec = _parse_test(entry, index, family, fail)
        # the id names the test's outputs (figures, a preprocessed copy): a file name
        _check_writable_id(spec.id, campaign)
        if spec.id in seen:
            raise fail("duplicate test id", test=spec.id)
        seen.add(spec.id)
        _check_data_file(spec, root, campaign)
        tests.append(spec)
    return tests


def _check_data_file(spec: TestSpec, root: Path, campaign: str) -> None:
    """A test's data file has a supported extension and exists under ``root``."""
    file_path = root / spec.file
    if Path(spec.file).suffix.lower() not in DATA_EXTENSIONS:
        raise CampaignError(
            f"unsupported file extension {Path(spec.file).suffix!r}; "
            f"use {' or '.join(DATA_EXTENSIONS)}",
            campaign=campaign,
            test=spec.id,
            path=file_path,
        )
    if not file_path.is_file():
        raise CampaignError(
            f"data file not found (file: {spec.file})",
            campaign=campaign,
            test=spec.id,
            path=file_path,
        )


# A magnitude no rig's channel reaches in SI units; loggers write 1e30, 9.9e37 (NI) or
# FLT_MAX for a missing sample, which would pass as finite data.
FILL_VALUE = 1e15


def _not_utf8(file_path: Path, fail) -> CampaignError:
    """Where a CSV file stops being UTF-8 (pandas says neither the row nor the byte)."""
    raw = file_path.read_bytes()
    try:
        raw.decode("utf-8")
        return fail("not UTF-8 text; save the file as UTF-8 or plain ASCII")
    except UnicodeDecodeError as bad:
        line = raw[:bad.start].count(b"\n")  # line 0 is the header, line k data row k
        what = f"not UTF-8 text (byte 0x{raw[bad.start]:02x}); save the file as UTF-8 or ASCII"
        return fail(what, row=line) if line else fail(what + " (in the header line)")


def _header_names(file_path: Path, suffix: str) -> list[str]:
    """The header's names as written (pandas renames a repeated one to ``name.1``)."""
    if suffix != ".csv":
        return []
    with open(file_path, encoding="utf-8", errors="replace") as fh:
        return [c.strip() for c in next(csv.reader(fh), [])]


def _check_controls_held_out(tests: list[TestSpec], root: Path, campaign: str) -> None:
    """A control test that reads an identification test's file is not held out."""
    fitted = {(root / t.file).resolve(): t.id for t in tests if t.role == "identification"}
    for t in tests:
        other = fitted.get((root / t.file).resolve()) if t.role == "control" else None
        if other is not None:
            raise CampaignError(
                f"control test reads the file of identification test '{other}' "
                f"(file: {t.file}); a control must be data the fit never sees",
                campaign=campaign, test=t.id, path=root / t.file)


def _known_number(value: Any, what: str, fail) -> float:
    # bool is an int subclass but `true` is never a physical value.
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise fail(f"{what} is {value!r}, not a number")
    if not math.isfinite(value):
        raise fail(f"{what} is {value!r}, not a finite number")
    return float(value)


def _parse_known(raw: Any, fail) -> tuple[dict[str, float], dict[str, float]]:
    """``known:`` as (values, prior sigmas): a number is fixed, ``{value, sigma}`` a prior."""
    if raw is None:
        return {}, {}
    if not isinstance(raw, dict):
        raise fail(f"'known' must be a mapping, got {type(raw).__name__}")
    known: dict[str, float] = {}
    priors: dict[str, float] = {}
    for key, value in raw.items():
        key = str(key)
        if not isinstance(value, dict):
            known[key] = _known_number(value, f"known value '{key}'", fail)
            continue
        missing = [k for k in ("value", "sigma") if k not in value]
        if missing:
            raise fail(f"known prior '{key}' lacks {' and '.join(missing)}: a prior is "
                       "{value: ..., sigma: ...} in SI units")
        known[key] = _known_number(value["value"], f"known prior '{key}': value", fail)
        sigma = _known_number(value["sigma"], f"known prior '{key}': sigma", fail)
        if not sigma > 0.0:
            raise fail(f"known prior '{key}': sigma is {sigma!r}; it must be > 0 "
                       "(a value known exactly is written as a plain number)")
        if known[key] == 0.0:
            raise fail(f"known prior '{key}': value is 0; a prior needs a non-zero centre")
        priors[key] = sigma
    return known, priors


# A stated value this far outside the range the model takes for its parameter is a unit
# slip (mm written as m, g as kg), not a rig: 100x is beyond any rig of the family.
KNOWN_RANGE_FACTOR = 100.0


def _check_known_ranges(known: dict[str, float], family: SystemFamily, fail) -> None:
    """Refuse a stated value no rig can have: below zero (or at zero) for a quantity that
    is positive by nature, or a unit slip outside the model's range for it. Names that
    are no parameter of the model are left to identification (it says they are unused)."""
    try:
        model = family.model()
    except KeyError:
        return
    for key, value in known.items():
        if key not in model.param_index:
            continue
        spec = model.spec(key)
        span = f"the model's range for it is {spec.lower:g} to {spec.upper:g} {spec.unit}"
        if (spec.lower > 0.0 and value <= 0.0) or (spec.lower >= 0.0 and value < 0.0):
            sign = "> 0" if spec.lower > 0.0 else "≥ 0"
            raise fail(f"known value '{key}' is {value:g} {spec.unit}; it must be {sign} "
                       f"({span})")
        if ((spec.upper > 0.0 and value > KNOWN_RANGE_FACTOR * spec.upper)
                or (spec.lower > 0.0 and value < spec.lower / KNOWN_RANGE_FACTOR)):
            raise fail(f"known value '{key}' is {value:g} {spec.unit}, more than "
                       f"{KNOWN_RANGE_FACTOR:g}x outside what a rig has ({span}); a unit slip?")


def _parse_test(entry: Any, index: int, family: SystemFamily, fail) -> TestSpec:
    if not isinstance(entry, dict):
        raise fail(f"tests entry {index + 1} must be a mapping, got {type(entry).__name__}")
    raw_id = entry.get("id")
    if raw_id is None:
        raise fail(f"tests entry {index + 1}: missing key 'id'")
    if not _is_scalar(raw_id) or str(raw_id).strip() == "":
        raise fail(f"tests entry {index + 1}: 'id' must be a non-empty string")
    test_id = str(raw_id)

    for key in _REQUIRED_TEST_KEYS:
        if entry.get(key) is None:
            raise fail(f"missing key '{key}'", test=test_id)
    for key in ("file", "scenario", "motor", "role"):
        if not isinstance(entry[key], str):
            raise fail(f"'{key}' must be a string, got {entry[key]!r}", test=test_id)

    scenario = entry["scenario"]
    if scenario not in family.scenarios:
        raise fail(
            f"unknown scenario '{scenario}'; valid for {family.name}: "
            f"{', '.join(family.scenarios)}",
            test=test_id,
        )
    role = entry["role"]
    if role not in ROLES:
        raise fail(f"role is '{role}', expected one of: {', '.join(ROLES)}", test=test_id)
    motor = entry["motor"]
    if motor not in family.motor_modes:
        raise fail(
            f"motor is '{motor}', expected one of: {', '.join(family.motor_modes)}",
            test=test_id,
        )
    profile = entry["input"]
    if not isinstance(profile, dict):
        raise fail(f"'input' must be a mapping, got {profile!r}", test=test_id)

    speed = entry.get("vehicle_speed_kph")
    if speed is not None:
        if isinstance(speed, bool) or not isinstance(speed, (int, float)):
            raise fail(f"vehicle_speed_kph is {speed!r}, not a number", test=test_id)
        speed = float(speed)
    mode = entry.get("assist_mode")
    if mode is not None:
        mode = str(mode)

    return TestSpec(
        id=test_id,
        file=entry["file"],
        scenario=scenario,
        input=dict(profile),
        motor=motor,
        role=role,
        vehicle_speed_kph=speed,
        assist_mode=mode,
        extra={k: v for k, v in entry.items() if k not in _TEST_KEYS},
    )


def _is_scalar(value: Any) -> bool:
    return isinstance(value, (str, int, float)) and not isinstance(value, bool)


def _separator_hint(df: pd.DataFrame) -> str:
    """Why a header may read as one column: the file is not separated by commas."""
    if len(df.columns) != 1:
        return ""
    head = df.columns[0]
    sep = next((c for c in (";", "\t", "|") if c in head), None)
    if sep is None:
        return ""
    return (f" (the header reads as one column {head[:60]!r}: campaign files are "
            f"comma-separated, and this one looks separated by {sep!r})")


def _load_test_data(
    file_path: Path, spec: TestSpec, family: SystemFamily, campaign: str
) -> pd.DataFrame:
    """Read one test file and check it against the family's channel table."""

    def fail(message: str, column: str | None = None, row: int | None = None) -> CampaignError:
        return CampaignError(
            message, campaign=campaign, test=spec.id, column=column, row=row, path=file_path
        )

    suffix = file_path.suffix.lower()
    if suffix not in DATA_EXTENSIONS:
        raise fail(f"unsupported file extension {file_path.suffix!r}")
    if not file_path.is_file():
        raise fail(f"data file not found (file: {spec.file})")
    df = _read_table(file_path, suffix, fail)
    # "time_s, steering_angle_rad" (a space after each comma, as some exports write it)
    df.columns = [str(c).strip() for c in df.columns]
    names = _header_names(file_path, suffix)
    twice = sorted({c for c in names if names.count(c) > 1})
    if twice:
        raise fail("column given twice in the header; which one is meant is not known",
                   column=twice[0])
    present = [ch.name for ch in family.channels if ch.name in df.columns]
    _as_numbers(df, present, fail)
    for col in family.required_channels(spec.scenario):
        if col not in df.columns:
            raise fail(f"missing column required for scenario '{spec.scenario}'"
                       + _separator_hint(df), column=col)
    if len(df) < MIN_SAMPLES:
        raise fail(f"only {len(df)} samples; at least {MIN_SAMPLES} are needed")
    _check_measurements(df, present, fail)
    _check_time(df[family.time_channel].to_numpy(dtype=float), family.time_channel, fail)
    return df


def _read_table(file_path: Path, suffix: str, fail: Callable[..., CampaignError]
                ) -> pd.DataFrame:
    try:
        if suffix == ".csv":
            return pd.read_csv(file_path)
        return pd.read_parquet(file_path)
    except pd.errors.EmptyDataError as exc:
        raise fail("file is empty (no header line)") from exc
    except pd.errors.ParserError as exc:  # "Expected 4 fields in line 1501, saw 5"
        found = re.search(r"Expected (\d+) fields in line (\d+), saw (\d+)", str(exc))
        if not found:
            raise fail(f"cannot read csv file: {exc}") from exc
        want, line, got = (int(g) for g in found.groups())
        raise fail(f"{got} fields where the header has {want}", row=line - 1) from exc
    except UnicodeDecodeError as exc:
        raise _not_utf8(file_path, fail) from exc
    except Exception as exc:
        raise fail(f"cannot read {suffix[1:]} file: {type(exc).__name__}: {exc}") from exc


def _as_numbers(df: pd.DataFrame, present: list[str], fail: Callable[..., CampaignError]
                ) -> None:
    """Known channels must be numeric (converted in place); name the first cell that is not."""
    for col in present:
        series = df[col]
        if pd.api.types.is_numeric_dtype(series) and not pd.api.types.is_bool_dtype(series):
            df[col] = series.astype("float64")
            continue
        numeric = pd.to_numeric(series, errors="coerce")
        bad = np.flatnonzero((numeric.isna() & series.notna()).to_numpy())
        if bad.size:
            i = int(bad[0])
            raise fail(f"value {series.iloc[i]!r} is not a number", column=col, row=i + 1)
        df[col] = numeric.astype("float64")


def _check_measurements(df: pd.DataFrame, present: list[str],
                        fail: Callable[..., CampaignError]) -> None:
    """No NaN, inf or logger fill value in a known channel."""
    for col in present:
        values = df[col].to_numpy(dtype=float)
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            i = int(bad[0])
            what = "NaN" if np.isnan(values[i]) else ("inf" if values[i] > 0 else "-inf")
            raise fail(f"value is {what}", column=col, row=i + 1)
        bad = np.flatnonzero(np.abs(values) >= FILL_VALUE)
        if bad.size:
            i = int(bad[0])
            raise fail(f"value {values[i]:.6g} is no measurement (a logger's fill value for "
                       "a missing sample?)", column=col, row=i + 1)


def _check_time(t: np.ndarray, time_col: str, fail: Callable[..., CampaignError]) -> None:
    """Time strictly increasing and uniform (within ``TIME_UNIFORMITY`` of the median step)."""
    dt = np.diff(t)
    # dt[i] sits between data rows i+1 and i+2 (1-based); blame the later one.
    bad = np.flatnonzero(dt <= 0)
    if bad.size:
        i = int(bad[0])
        raise fail(
            f"time is not strictly increasing ({t[i + 1]:.9g} s after {t[i]:.9g} s)",
            column=time_col,
            row=i + 2,
        )
    median = float(np.median(dt))
    bad = np.flatnonzero(np.abs(dt - median) > TIME_UNIFORMITY * median)
    if bad.size:
        i = int(bad[0])
        deviation = 100.0 * abs(dt[i] - median) / median
        raise fail(
            f"time is not uniform: step {dt[i]:.6g} s is {deviation:.3g} % off the median "
            f"{median:.6g} s (limit {100 * TIME_UNIFORMITY:g} %)",
            column=time_col,
            row=i + 2,
        )


# --------------------------------------------------------------------------- writing


def write_campaign(
    campaign_dir: str | Path,
    *,
    name: str,
    system: str,
    known: dict[str, float],
    tests: list[tuple[TestSpec, pd.DataFrame]],
    extra: dict | None = None,
    fmt: str = "csv",
    overwrite: bool = False,
    priors: dict[str, float] | None = None,
) -> Path:
    """Write a campaign directory atomically.

    Everything is written into a temporary sibling directory first and renamed
    into place, so readers never see a half-written campaign. With
    ``overwrite`` an existing target is removed only after the new campaign is
    complete.

    Parameters
    ----------
    campaign_dir
        Target directory; its parent is created if needed.
    name, system, known
        Top-level ``campaign.yaml`` values.
    priors
        Name -> sigma of the ``known`` values to write as a prior ``{value, sigma}``.
    tests
        ``(spec, frame)`` pairs in the order they should appear. Each frame is
        written to ``tests/<id>.<fmt>`` (``spec.file`` is replaced by that path)
        without its index. CSV floats are written at full ``repr`` precision so
        that reading gives back the same values.
    extra
        Further top-level keys, written after ``known``.
    fmt
        ``"csv"`` or ``"parquet"``.
    overwrite
        Replace an existing ``campaign_dir``.

    Returns
    -------
    Path
        The campaign directory.

    Raises
    ------
    CampaignError
        On bad arguments, an existing target without ``overwrite``, or I/O failure.
    """
    target = Path(campaign_dir)
    if fmt not in ("csv", "parquet"):
        raise CampaignError(f"fmt must be 'csv' or 'parquet', got {fmt!r}", campaign=name)
    if target.exists() and not overwrite:
        raise CampaignError("already exists (pass overwrite=True)", campaign=name, path=target)
    _check_tests_to_write(tests, name)
    doc = _campaign_doc(name, system, known, priors, extra)
    doc["tests"] = [_test_entry(spec, f"tests/{spec.id}.{fmt}", name) for spec, _ in tests]
    tmp = target.parent / f".{target.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        _write_files(tmp, doc, tests, fmt)
        _swap_into_place(tmp, target)
    except CampaignError:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    except Exception as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise CampaignError(
            f"cannot write campaign: {type(exc).__name__}: {exc}", campaign=name, path=target
        ) from exc
    return target


def _check_tests_to_write(tests: list[tuple[TestSpec, pd.DataFrame]], name: str) -> None:
    """Writable, unique ids, each with a data frame."""
    seen: set[str] = set()
    for spec, frame in tests:
        _check_writable_id(spec.id, name)
        if spec.id in seen:
            raise CampaignError("duplicate test id", campaign=name, test=spec.id)
        seen.add(spec.id)
        if not isinstance(frame, pd.DataFrame):
            raise CampaignError(
                f"data must be a pandas DataFrame, got {type(frame).__name__}",
                campaign=name,
                test=spec.id,
            )


def _campaign_doc(name: str, system: str, known: dict[str, float],
                  priors: dict[str, float] | None, extra: dict | None) -> dict[str, Any]:
    """``campaign.yaml``'s keys before ``tests``: a known value with a prior as
    ``{value, sigma}``, then the extra keys (none may clash with the format's)."""
    doc: dict[str, Any] = {
        "format": FORMAT,
        "name": name,
        "system": system,
        "known": {str(k): ({"value": float(v), "sigma": float(priors[k])}
                           if priors and k in priors else float(v))
                  for k, v in known.items()},
    }
    for key, value in (extra or {}).items():
        if key in _TOP_KEYS:
            raise CampaignError(f"extra key '{key}' clashes with a format key", campaign=name)
        doc[key] = value
    return doc


def _write_files(tmp: Path, doc: dict[str, Any], tests: list[tuple[TestSpec, pd.DataFrame]],
                 fmt: str) -> None:
    """The campaign's files into the temporary folder ``tmp``."""
    (tmp / "tests").mkdir(parents=True)
    for spec, frame in tests:
        out = tmp / "tests" / f"{spec.id}.{fmt}"
        if fmt == "csv":
            # Default float formatting is repr: shortest text that reads back exactly.
            frame.to_csv(out, index=False)
        else:
            frame.to_parquet(out, index=False)
    text = yaml.safe_dump(_plain(doc), sort_keys=False, allow_unicode=True)
    (tmp / CAMPAIGN_FILE).write_text(text, encoding="utf-8")


def _check_writable_id(test_id: str, campaign: str) -> None:
    # The id becomes a file name; refuse anything that would escape tests/.
    if (
        not isinstance(test_id, str)
        or not test_id
        or test_id.startswith(".")
        or any(c in test_id for c in "/\\:\0")
    ):
        raise CampaignError(
            "test id must be a non-empty file name without '/', '\\', ':' or a leading '.'",
            campaign=campaign,
            test=str(test_id),
        )


def _test_entry(spec: TestSpec, file: str, campaign: str) -> dict[str, Any]:
    entry: dict[str, Any] = {
        "id": spec.id,
        "file": file,
        "scenario": spec.scenario,
        "input": dict(spec.input),
        "motor": spec.motor,
        "role": spec.role,
    }
    if spec.vehicle_speed_kph is not None:
        entry["vehicle_speed_kph"] = float(spec.vehicle_speed_kph)
    if spec.assist_mode is not None:
        entry["assist_mode"] = spec.assist_mode
    for key, value in spec.extra.items():
        if key in _TEST_KEYS:
            raise CampaignError(
                f"extra key '{key}' clashes with a format key", campaign=campaign, test=spec.id
            )
        entry[key] = value
    return entry


def _plain(value: Any) -> Any:
    """Turn numpy scalars, tuples and paths into types ``yaml.safe_dump`` accepts."""
    if isinstance(value, dict):
        return {_plain(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def _swap_into_place(tmp: Path, target: Path) -> None:
    if not target.exists():
        os.replace(tmp, target)
        return
    old = target.parent / f".{target.name}.old-{uuid.uuid4().hex[:8]}"
    os.replace(target, old)
    try:
        os.replace(tmp, target)
    except OSError:
        os.replace(old, target)  # put the previous campaign back
        raise
    if old.is_dir() and not old.is_symlink():
        shutil.rmtree(old, ignore_errors=True)
    else:
        old.unlink(missing_ok=True)


# --------------------------------------------------------------------------- summary



def _barely_moves(x: np.ndarray, dt_s: float) -> str:
    """A description when the input's range is under ten times what its sensor resolves
    (noise or quantum); empty otherwise."""
    res = signal_resolution(x, dt_s)
    span = float(np.ptp(x))
    if span <= 0:
        return "it stays at one value"
    if span < 10 * res:
        return f"range {span:.3g}, {span / res:.1f}× its noise or quantum"
    return ""


# An isolated sample whose jump off its neighbours' mean is this many times the channel's
# 90th-percentile jump (a level a few glitches, each three jumps wide, cannot move), while
# the neighbours agree with each other (no step), is a glitch.
SPIKE_FACTOR = 1000.0
# ... and so is a run of up to this many such samples (a dropped word, a bus hiccup)
MAX_GLITCH_SAMPLES = 3
# Sample rates no rig's log has: below, a time column in ms read as s (500 Hz logged reads
# as 0.5 Hz, and a fit on it runs for hours); above, one in another unit (µs, ns).
MIN_PLAUSIBLE_RATE_HZ = 20.0
MAX_PLAUSIBLE_RATE_HZ = 1e6
# input kinds of campaign-format.md; another is read (the profile is informative) and said
INPUT_KINDS = ("sine", "sweep", "ramp", "triangle", "step", "impact", "random", "recorded")


def isolated_spikes(x: np.ndarray) -> list[int]:
    """First rows (0-based) of glitches: one sample, or a burst of up to ``MAX_GLITCH_SAMPLES``,
    each far off the samples around it, that a fit would chase. A step is no glitch (the
    samples around it differ by the jump). A logger that drops a word writes two or three
    bad samples in a row; a check of single samples alone saw none of them (each bad
    sample's neighbour was bad too)."""
    x = np.asarray(x, dtype=float)
    if x.size < 5:
        return []
    scale = float(np.percentile(np.abs(x[1:-1] - 0.5 * (x[:-2] + x[2:])), 90.0))
    if scale <= 0.0:
        return []
    rows: set[int] = set()
    for width in range(1, MAX_GLITCH_SAMPLES + 1):
        rows.update(_bursts(x, width, scale))
    # a burst is reported once, by its first row
    return sorted(r for r in rows if r - 1 not in rows)


def _bursts(x: np.ndarray, width: int, scale: float) -> list[int]:
    """First rows of runs of ``width`` samples all far off the mean of the two samples
    around the run, those two agreeing with each other."""
    n = x.size
    if n < width + 4:
        return []
    before, after = x[: n - width - 1], x[width + 1:]
    mean, sides = 0.5 * (before + after), np.abs(after - before)
    off = np.min([np.abs(x[1 + j: n - width + j] - mean) for j in range(width)], axis=0)
    return [int(i) + 1 for i in np.flatnonzero((off > SPIKE_FACTOR * scale)
                                               & (off > 10.0 * sides))]


def _spike_warnings(test_id: str, channels: dict[str, np.ndarray]) -> list[str]:
    """One line per channel that holds glitches, naming the first's row."""
    out = []
    for ch, x in channels.items():
        rows = isolated_spikes(x)
        if rows:
            more = f" (and {len(rows) - 1} more)" if len(rows) > 1 else ""
            out.append(f"test '{test_id}': channel '{ch}', row {rows[0] + 1}: value "
                       f"{x[rows[0]]:.6g} is a glitch far off its neighbours (one sample or "
                       f"a burst of up to {MAX_GLITCH_SAMPLES}){more}; the fit will chase it")
    return out


def _rate_warnings(test_id: str, dt_s: float, time_channel: str) -> list[str]:
    """A line when a test's sample rate is implausible for a rig: time in another unit?"""
    rate = 1.0 / dt_s
    if rate < MIN_PLAUSIBLE_RATE_HZ:
        return [f"test '{test_id}': sample rate {rate:.3g} Hz, too slow for the rig's "
                f"dynamics; is {time_channel} in seconds (milliseconds read as seconds slow "
                "a log 1000x)?"]
    if rate > MAX_PLAUSIBLE_RATE_HZ:
        return [f"test '{test_id}': sample rate {rate:.3g} Hz, faster than any rig's logger; "
                f"is {time_channel} in seconds?"]
    return []


def data_warnings(campaign: Campaign, test_id: str) -> list[str]:
    """What a test's data holds that a fit would take at face value and should not: a
    sample rate no rig logs at, single-sample glitches. The data is read as it is; `mbst
    check` and identification say these lines."""
    family = campaign.family
    df = campaign.frame(test_id)
    logged = [ch.name for ch in family.channels
              if ch.name in df.columns and ch.name != family.time_channel]
    return (_rate_warnings(test_id, campaign.sample_time_s(test_id), family.time_channel)
            + _spike_warnings(test_id, {c: df[c].to_numpy(dtype=float) for c in logged}))


# the columns of the tests table in ``mbst check``; the numeric ones are right-aligned
_SUMMARY_COLUMNS = (
    "id",
    "scenario",
    "motor",
    "role",
    "input",
    "duration_s",
    "rate_hz",
    "samples",
    "channels",
)
_NUMERIC_COLUMNS = {"duration_s", "rate_hz", "samples"}


def summarize_campaign(campaign: Campaign) -> str:
    """Human-readable overview for ``mbst check``.

    Loads any test data not yet loaded (so it raises :class:`CampaignError` on
    a bad file, like :func:`read_campaign`).

    Returns
    -------
    str
        Name, system, path, known values, a table of tests (id, scenario,
        motor, role, input kind, duration = last minus first time stamp,
        sample rate = 1 / median dt, samples, known channels present), counts
        per scenario and per role, and warnings.
    """
    lines = _summary_heading(campaign)
    rows: list[list[str]] = []
    notes: list[str] = []
    for spec in campaign.tests:
        df = campaign.frame(spec.id)
        dt = campaign.sample_time_s(spec.id)
        rows.append(_summary_row(campaign.family, spec, df, dt))
        notes += _test_notes(campaign, spec, df, dt)
    lines.append(f"tests ({len(campaign.tests)}):")
    lines += _aligned_table(list(_SUMMARY_COLUMNS), rows)
    lines += notes
    lines += _summary_counts(campaign)
    return "\n".join(lines)


def _summary_heading(campaign: Campaign) -> list[str]:
    """Name, system, path, the known values (priors with their sigma) and extra keys."""
    lines = [
        f"campaign: {campaign.name}",
        f"system:   {campaign.system}",
        f"path:     {campaign.path}",
    ]
    if campaign.known:
        lines.append("known:")
        width = max(len(k) for k in campaign.known)
        lines += [f"  {k:<{width}} = {v:.6g}"
                  + (f" ± {campaign.priors[k]:.3g} (prior)" if k in campaign.priors else "")
                  for k, v in campaign.known.items()]
    else:
        lines.append("known:    (none)")
    for key, value in campaign.extra.items():
        lines.append(f"{key}: {value}")
    return lines


def _summary_row(family: SystemFamily, spec: TestSpec, df: pd.DataFrame,
                 dt: float) -> list[str]:
    """One test's cells of the tests table, in the order of ``_SUMMARY_COLUMNS``."""
    channel_names = [ch.name for ch in family.channels]
    t = df[family.time_channel].to_numpy(dtype=float)
    channels = [c for c in channel_names if c in df.columns and c != family.time_channel]
    return [
        spec.id,
        spec.scenario,
        spec.motor,
        spec.role,
        spec.input_kind or "?",
        f"{t[-1] - t[0]:.3f}",
        f"{1.0 / dt:.1f}",
        str(len(df)),
        ",".join(channels),
    ]


def _test_notes(campaign: Campaign, spec: TestSpec, df: pd.DataFrame, dt: float) -> list[str]:
    """Lines below the table for one test: extra columns kept, and warnings about its
    data, its input kind and an input that barely moves."""
    family = campaign.family
    channel_names = [ch.name for ch in family.channels]
    notes = []
    other = [c for c in df.columns if c not in channel_names]
    if other:
        notes.append(f"  {spec.id}: extra columns kept: {', '.join(other)}")
    notes += [f"WARNING: {w}" for w in data_warnings(campaign, spec.id)]
    if spec.input_kind not in (None, *INPUT_KINDS):
        notes.append(f"WARNING: test '{spec.id}': input kind '{spec.input_kind}' is none "
                     f"of {', '.join(INPUT_KINDS)}; the profile is read as informative "
                     "(the model is driven by the measured angle)")
    still = _barely_moves(df[family.input_channel].to_numpy(dtype=float), dt)
    if still:
        notes.append(f"WARNING: test '{spec.id}': its input {family.input_channel} "
                     f"barely moves ({still}); a model's FIT on it measures the noise")
    return notes


def _aligned_table(header: list[str], rows: list[list[str]]) -> list[str]:
    """Header and rows as indented lines, columns padded to their widest cell (numeric
    columns right-aligned), trailing blanks cut."""
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]

    def fmt_row(cells: list[str]) -> str:
        out = [c.rjust(w) if h in _NUMERIC_COLUMNS else c.ljust(w)
               for c, w, h in zip(cells, widths, header)]
        return "  " + "  ".join(out).rstrip()

    return [fmt_row(header)] + [fmt_row(r) for r in rows]


def _summary_counts(campaign: Campaign) -> list[str]:
    """Tests per scenario (in the family's order) and per role, and a warning for a
    role no test has."""
    by_scenario = Counter(s.scenario for s in campaign.tests)
    ordered = [s for s in campaign.family.scenarios if s in by_scenario]
    lines = ["per scenario: " + ", ".join(f"{s} {by_scenario[s]}" for s in ordered)]
    by_role = Counter(s.role for s in campaign.tests)
    lines.append("per role: " + ", ".join(f"{r} {by_role.get(r, 0)}" for r in ROLES))
    if not by_role.get("identification"):
        lines.append("WARNING: no identification test; nothing can be fitted")
    if not by_role.get("control"):
        lines.append("WARNING: no control test; correlation of a fitted model cannot be measured")
    return lines
