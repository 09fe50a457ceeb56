"""``mbst plan --resolve``: the next tests that let discovery decide what it left open.

Seed 000's loop, closed: discovery's resolution step states which catalogue
pairs the campaign's tests cannot show; here the planner designs the tests
that would (``questions`` → ``candidates`` → ``design``), predicts the
separation before and after, and writes the campaign with them appended
(``report``). docs/loop.md has the method and its proof on the bench.
"""

from mbst.plan.resolve.questions import ResolveError
from mbst.plan.resolve.report import write_resolve
from mbst.plan.resolve.run import ResolveResult, resolve

__all__ = ["ResolveError", "ResolveResult", "resolve", "write_resolve"]
