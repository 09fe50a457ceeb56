"""What discovery left open, as questions a test can answer.

A *question* is one catalogue pair at one size: "would these tests name
``effect`` in ``component`` if the rig had it at this size?" Discovery's
resolution step answers it for the campaign's own tests (``resolution`` in
``discovery.json``); the pairs it marks as not resolved at the catalogue's
realistic size are the open questions, and an engineer may ask more
(``--target``: a production-size backlash, a smaller asymmetry).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mbst.core.model import EffectSpec, ModelDefinition
from mbst.discovery.rounds.resolution import scaled_size


class ResolveError(ValueError):
    """A discovery record or a target the resolve step cannot read (message names it)."""


@dataclass
class Question:
    """One catalogue pair at one size, with what the campaign predicts of it."""

    spec: EffectSpec
    stage: str
    values: dict[str, float]  # model parameter -> value at the size asked
    reason: str
    headline: dict[str, float] = field(default_factory=dict)
    # discovery's own prediction on the campaign (share of the stage cost, ΔAIC)
    before: tuple[float, float] | None = None

    @property
    def key(self) -> str:
        return self.spec.key

    def label(self) -> str:
        size = ", ".join(f"{h} {v:.4g}" for h, v in self.headline.items())
        return f"{self.spec.effect} in {self.spec.component} ({size})"


def parse_target(text: str, model: ModelDefinition) -> tuple[EffectSpec, dict[str, float]]:
    """``EFFECT:COMPONENT[:headline=value,...]`` → the pair and its parameters at that size."""
    parts = text.split(":")
    if len(parts) < 2:
        raise ResolveError(f"--target '{text}': expected EFFECT:COMPONENT[:param=value,...]")
    key = f"{parts[0]}:{parts[1]}"
    if key not in model.effects:
        raise ResolveError(f"--target '{text}': no pair '{key}' in the {model.name} catalogue "
                           f"(known: {', '.join(model.effects)})")
    spec = model.effects[key]
    values = dict(spec.default_size)
    for item in filter(None, (":".join(parts[2:])).split(",")):
        name, _, raw = item.partition("=")
        if name not in spec.headline:
            raise ResolveError(f"--target '{text}': '{name}' is not a parameter of {key} "
                               f"(known: {', '.join(spec.headline)})")
        try:
            values[spec.headline[name]] = float(raw)
        except ValueError:
            raise ResolveError(f"--target '{text}': {name}={raw!r} is not a number") from None
    return spec, values


def _headline(spec: EffectSpec, values: dict[str, float]) -> dict[str, float]:
    return {h: float(values[n]) for h, n in spec.headline.items()}


def open_questions(record: dict, model: ModelDefinition, targets: list[str]
                   ) -> tuple[list[Question], list[str]]:
    """The pairs discovery marked as not resolved at their realistic size, then ``targets``;
    and notes on targets that need no test (discovery named them already).

    A pair whose component acts in no tested cut-out (``stage`` None) is no question for
    this step: it needs a cut-out the campaign lacks (``mbst plan`` chooses cut-outs).
    """
    out: list[Question] = []
    notes: list[str] = []
    named = {f"{f['effect']}:{f['component']}": f for f in record.get("findings", [])}
    stages: dict[str, str] = {}
    for r in record.get("resolution", []):
        key = f"{r['effect']}:{r['component']}"
        if key not in model.effects or r.get("stage") is None:
            continue
        stages[key] = r["stage"]
        m = r.get("resolved_from_multiple")
        if m is not None and m <= 1.0:
            continue
        spec = model.effects[key]
        values = scaled_size(spec, model, 1.0)
        at = next((s for s in r.get("sizes", []) if s["multiple"] == 1.0), None)
        out.append(Question(spec, r["stage"], values,
                            "not resolved at its realistic size", _headline(spec, values),
                            (at["predicted_relative_gain"], at["predicted_aic_delta"])
                            if at else None))
    for text in targets:
        spec, values = parse_target(text, model)
        if spec.key in named:
            size = ", ".join(f"{k} {v:.4g}" for k, v in named[spec.key]["parameters"].items())
            notes.append(f"--target {text}: discovery named it already ({size}, confidence "
                         f"{named[spec.key].get('confidence') or 0:.2f}); no test needed")
            continue
        if spec.key not in stages:
            raise ResolveError(f"--target '{text}': {spec.key} acts in no cut-out of this "
                               "campaign")
        out = [q for q in out if q.key != spec.key]
        out.append(Question(spec, stages[spec.key], values, "asked (--target)",
                            _headline(spec, values)))
    return out, notes
