"""Recruiting-level rules of prioritized IK (Raunhardt & Boulic 2007, eqs. 3-5).

For priority levels ``a`` above ``b``::

    (3)  Rec(T_b) & Anc(T_a)  <=  Rec(T_a)
    (4)  (Rec(T_b) | Coup(Rec(T_b))) & (Anc(T_a) | Coup(Rec(T_a)))  <=  Rec(T_a)
    (5)  U_i Coup(Rec(T_i))  <=  U_i Rec(T_i)

``Coup(R)`` is the set of coordinates coupled to ``R`` through the constraint
graph (transitively).  `check_recruiting` reports every violation.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from kinematics.algorithms.constraints import ConstraintSet
from kinematics.algorithms.tasks import Task
from lowerlimb.errors import InputError

__all__ = ["RecruitingError", "RecruitingReport", "check_recruiting", "task_sets"]


class RecruitingError(InputError):
    """A task set violates the recruiting-level rules (eqs. 3-5 of the seed)."""


@dataclass(frozen=True)
class RecruitingReport:
    """Result of `check_recruiting`: ``violations`` is a tuple of one-line messages."""

    violations: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return not self.violations

    def raise_if_violated(self, source: str = "tasks") -> None:
        if self.violations:
            raise RecruitingError(source, "recruiting-level rules violated: " + "; ".join(self.violations))


def task_sets(task: Task, names: Sequence[str]) -> tuple[set[str], set[str]]:
    anc = set(task.ancestors) if task.ancestors is not None else set(names)
    rec = set(task.recruited) if task.recruited is not None else set(anc)
    return rec, anc


def check_recruiting(tasks: Sequence[Task], constraints: ConstraintSet) -> RecruitingReport:
    """Check the recruiting-level conditions (eqs. 3-5 of Raunhardt & Boulic 2007).

    For every pair of levels ``a`` (higher priority) and ``b`` (lower)::

        (3) Rec_b & Anc_a <= Rec_a
        (4) (Rec_b | Coup(Rec_b)) & (Anc_a | Coup(Rec_a)) <= Rec_a
        (5) U Coup(Rec_i) <= U Rec_i

    Rec, Anc of a level are the unions over its tasks.  Coup(R) contains the
    coordinates linked to R through the constraint graph (equalities and user
    inequalities, transitively), R excluded.
    """
    names = constraints.coordinate_names
    known = set(names)
    violations = []
    for t in tasks:
        for label, group in (("recruited", t.recruited), ("ancestors", t.ancestors)):
            missing = sorted(set(group or ()) - known)
            if missing:
                violations.append(f"task {t.name!r}: {label} coordinate(s) {missing[:5]} do not exist")
    if violations:
        return RecruitingReport(tuple(violations))
    groups = [{names[i] for i in g} for g in constraints.coupled_groups()]

    def coup(rec: set[str]) -> set[str]:
        out = set()
        for g in groups:
            if g & rec:
                out |= g
        return out - rec

    levels: dict[int, tuple[set[str], set[str], list[str]]] = {}
    for t in tasks:
        rec, anc = task_sets(t, names)
        r, a, nm = levels.setdefault(t.priority, (set(), set(), []))
        r |= rec
        a |= anc
        nm.append(t.name)
    order = sorted(levels)

    def show(s):
        s = sorted(s)
        return str(s[:4])[:-1] + (", ...]" if len(s) > 4 else "]")

    for ia, pa in enumerate(order):
        rec_a, anc_a, names_a = levels[pa]
        for pb in order[ia + 1:]:
            rec_b, anc_b, names_b = levels[pb]
            bad3 = (rec_b & anc_a) - rec_a
            if bad3:
                violations.append(f"eq. (3): level {pb} {names_b} recruits {show(bad3)} which are ancestors "
                                  f"of level {pa} {names_a} but not recruited by it")
            bad4 = ((rec_b | coup(rec_b)) & (anc_a | coup(rec_a))) - rec_a - bad3
            if bad4:
                violations.append(f"eq. (4): through coupling, level {pb} {names_b} moves {show(bad4)} which "
                                  f"level {pa} {names_a} reaches but does not recruit")
    all_rec = set().union(*(levels[p][0] for p in order)) if order else set()
    bad5 = coup(all_rec) - all_rec
    if bad5:
        violations.append(f"eq. (5): coordinates {show(bad5)} are coupled to recruited ones but recruited by no task")
    return RecruitingReport(tuple(violations))

