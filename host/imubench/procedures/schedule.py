"""Which move the fixture's plate makes next, when several boards on it ask for different ones.

    next_move(needs)   -> Move: the attitude or turn to present, and the boards it serves

Each board still running on the plate asks for one thing at a time (a Need):

    "pose"    any one of the attitudes it still misses (an adaptive multi-position session
              takes them in any order; `prefer` is the one that helps its fit most)
    "turn"    one turntable turn (key: axis and rate)
    "verify"  one verification attitude (key: its name), after its fit and write-back

The rules (issue 24, docs/production.md "Many boards on one fixture"):

1. Phases in order: while any board still needs attitudes ("pose"), the plate presents
   attitudes; then turns; only then verification. A board that is done with its attitudes
   waits for the others (its verification never moves the plate away from an attitude
   another board still needs).
2. Within the phase, the move that serves the most boards at once: the attitude in the most
   boards' missing sets (the union of what they miss, most shared first); ties go to the
   attitude most boards would pick themselves (`prefer`), then to the plan's order (the
   order of the missing lists), then to the lowest slot.
3. The move serves every board whose need it meets, whatever that board's phase.

Pure: no threads, no devices; fixture.Plate applies it, and tests drive it with arrays.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

#: the phases in the order the plate serves them
PHASES = ("pose", "turn", "verify")


@dataclass(frozen=True)
class Need:
    """What one board asks the plate for (see the module's doc)."""
    kind: str                     # "pose" | "turn" | "verify"
    keys: tuple                   # pose: the attitudes it still misses (names, plan order); else (the one key,)
    prefer: object | None = None  # pose: the attitude that helps its fit most

    def __post_init__(self):
        if self.kind not in PHASES:
            raise ValueError(f"unknown need {self.kind!r}")
        if not self.keys:
            raise ValueError(f"a {self.kind} need with nothing in it")

    def accepts(self, kind: str, key) -> bool:
        return kind == self.kind and key in self.keys


@dataclass(frozen=True)
class Move:
    kind: str                     # the phase of the move
    key: object                   # the attitude's name, or the turn's key
    serves: tuple                 # the slots whose need it meets (ascending)
    waiting: tuple                # the slots it leaves waiting (ascending)


def next_move(needs: Mapping[int, Need]) -> Move:
    """The plate's next move for the boards' needs {slot: Need} (every board still running
    has asked: a board at work elsewhere is not in `needs`, and the plate waits for it)."""
    if not needs:
        raise ValueError("no board asks for anything")
    phase = min((n.kind for n in needs.values()), key=PHASES.index)
    asking = {s: n for s, n in needs.items() if n.kind == phase}
    # candidates in a stable order: by lowest asking slot, then that slot's own order
    order: dict = {}
    for s in sorted(asking):
        for k in asking[s].keys:
            order.setdefault(k, len(order))

    def score(key) -> tuple:
        wanted = sum(1 for n in asking.values() if key in n.keys)
        preferred = sum(1 for n in asking.values() if n.prefer == key)
        return (-wanted, -preferred, order[key])

    key = min(order, key=score)
    serves = tuple(sorted(s for s, n in needs.items() if n.accepts(phase, key)))
    waiting = tuple(sorted(s for s in needs if s not in serves))
    return Move(phase, key, serves, waiting)


def still_needed(needs: Mapping[int, Need], kind: str = "pose") -> set:
    """The union of what the boards asking for `kind` still miss."""
    return {k for n in needs.values() if n.kind == kind for k in n.keys}
