"""What discovery left open, as questions a test can answer.

A *size question* is one catalogue pair at one size: "would these tests name
``effect`` in ``component`` if the rig had it at this size?" Discovery's
resolution step answers it for the campaign's own tests (``resolution`` in
``discovery.json``); the pairs it marks as not resolved at the catalogue's
realistic size are the open questions, and an engineer may ask more
(``--target``: a production-size backlash, a smaller asymmetry).

A *rival question* is a finding and a look-alike discovery did not rule out
(``alternatives`` of a finding: the winner was better in fewer than 95 % of
the resamples): "which of the two does the rig have?" Its two models are the
extended model as discovery left it and the same model with the named effect
off and the rival at the size its refit reached.

A *signature question* is an unexplained finding's channel read two ways
(``plan/resolve/signatures.py``): "does the structure follow this quantity or
that one?" It carries its fitted reading (``signature``) and no catalogue pair.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mbst.core.model import EffectSpec, ModelDefinition
from mbst.discovery.rounds.resolution import scaled_size


class ResolveError(ValueError):
    """A discovery record or a target the resolve step cannot read (message names it)."""


@dataclass
class Question:
    """One catalogue pair at one size, a finding against a look-alike, or an unexplained
    finding's two readings; with what the campaign predicts of it."""

    spec: EffectSpec | None  # None for a signature question
    stage: str
    values: dict[str, float]  # model parameter -> value at the size asked
    reason: str
    headline: dict[str, float] = field(default_factory=dict)
    # discovery's own prediction on the campaign (share of the stage cost, ΔAIC)
    before: tuple[float, float] | None = None
    # a rival question: the look-alike, and what turns the named model into its model
    # (the named effect off, the rival at its refitted size)
    rival: EffectSpec | None = None
    rival_values: dict[str, float] = field(default_factory=dict)
    # the share of discovery's resamples in which the finding beat the rival
    observed_share: float | None = None
    # the likelihood ratio the design must reach for this rival (design.calibrate_rivals)
    lr_needed: float | None = None
    # a signature question: the fitted reading (``signatures.Reading``)
    signature: Any = None

    @property
    def competing(self) -> bool:
        """Two models that both explain the stage: only their separation is judged."""
        return self.rival is not None or self.signature is not None

    @property
    def effect(self) -> str:
        return "unexplained" if self.spec is None else self.spec.effect

    @property
    def component(self) -> str:
        return self.signature.channel if self.spec is None else self.spec.component

    @property
    def rival_key(self) -> str | None:
        if self.signature is not None:
            return self.signature.rival
        return self.rival.key if self.rival is not None else None

    @property
    def free_count(self) -> int:
        """Parameters the question's effect adds (0 for two competing models)."""
        return 0 if self.competing else len(self.spec.free)

    @property
    def key(self) -> str:
        if self.signature is not None:
            return self.signature.key(self.stage)
        return self.spec.key if self.rival is None else f"{self.spec.key}|{self.rival.key}"

    def label(self) -> str:
        if self.signature is not None:
            return f"{self.signature.label()}, on {self.stage}"
        if self.rival is not None:
            return (f"{self.spec.effect} in {self.spec.component} or {self.rival.effect} in "
                    f"{self.rival.component}")
        size = ", ".join(f"{h} {v:.4g}" for h, v in self.headline.items())
        return f"{self.spec.effect} in {self.spec.component} ({size})"

    def models(self, p: np.ndarray, model: ModelDefinition
               ) -> tuple[np.ndarray, np.ndarray]:
        """The two competing parameter vectors around ``p`` (the model as it stands):
        (without, with) the effect for a size question, (rival, named) for a rival one."""
        other = np.array(p, float)
        for n, v in (self.rival_values if self.rival is not None else self.values).items():
            other[model.param_index[n]] = v
        return (other, np.array(p, float)) if self.rival is not None else \
            (np.array(p, float), other)


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
    return out + rival_questions(record, model), notes


def _refitted_size(record: dict, finding: dict, rival: EffectSpec) -> dict[str, float]:
    """The rival's parameters as its refit left them in the round that named the finding
    (its headline in the round's candidate rows), else its realistic size."""
    values = dict(rival.default_size)
    key = f"{finding['effect']}:{finding['component']}"
    for rnd in record.get("rounds", []):
        if rnd.get("accepted") != key:
            continue
        for c in rnd.get("candidates", []):
            if c.get("key") == rival.key:
                values.update({rival.headline[h]: float(v)
                               for h, v in (c.get("headline") or {}).items()
                               if h in rival.headline})
    return values


def rival_questions(record: dict, model: ModelDefinition) -> list[Question]:
    """A finding and each look-alike discovery did not rule out, unless that look-alike
    is named too (then both are in the model) or moves as one body with it
    (``indistinguishable_from``: no test of these cut-outs parts them)."""
    findings = record.get("findings", [])
    named = {f"{f['effect']}:{f['component']}" for f in findings}
    out = []
    for f in findings:
        key = f"{f['effect']}:{f['component']}"
        if key not in model.effects or not f.get("stage"):
            continue
        spec = model.effects[key]
        joint = set(f.get("indistinguishable_from") or [])
        for alt in f.get("alternatives") or []:
            same_body = alt["effect"] == f["effect"] and alt["component"] in joint
            if alt["key"] in named or same_body or alt["key"] not in model.effects:
                continue
            rival = model.effects[alt["key"]]
            values = {n: model.spec(n).default for n in spec.free}
            values.update(_refitted_size(record, f, rival))
            share = alt.get("winner_better_share")
            why = "a look-alike not ruled out" + (
                f" (the finding better in {100 * share:.0f} % of the resamples)"
                if share is not None else "")
            out.append(Question(spec, f["stage"], {}, why, _headline(rival, values),
                                rival=rival, rival_values=values, observed_share=share))
    return out
