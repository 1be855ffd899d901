"""The words every command uses for a run's results, so each number says what it is:
*training fitness* (Eq 12 on training trials), *best of generation g* (the fittest of one
generation on training) and the *champion* (the controller a completed run exports, chosen on
validation, with its held-out test figures)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from colony.client import SHORT_SHA

if TYPE_CHECKING:  # schemas.run builds its models when imported: not at `colony --help`
    from schemas.run import HeldOutScore, Proportion, ValidationScore


def training_progress(best_so_far: float | None, latest: float | None) -> str:
    """A progress bar's label: the best training fitness so far, which only rises, and the
    latest generation's best, which may fall (new trials every generation)."""
    if best_so_far is None or latest is None:
        return "training fitness: no generation yet"
    return f"training fitness: best so far {best_so_far:.3f} · last generation's best {latest:.3f}"


def chosen(fitness: float | None, validation: ValidationScore | None) -> str:
    """How the champion was chosen: its training fitness, and its validation."""
    training = "n/a" if fitness is None else f"{fitness:.4f}"
    v = validation
    if v is None:
        return f"training fitness {training} (rank 0; validation off)"
    return (
        f"training fitness {training} (rank {v.training_rank}); validation on {v.poses} poses x "
        f"{v.steps} steps: score {v.score:.4f}, stuck {v.stuck:.0%}, roaming {v.roaming:.0%}"
    )


def _interval(name: str, p: Proportion) -> str:
    return f"{name} {p.value:.0%} [{p.low:.0%}, {p.high:.0%}]"


def held_out(test: HeldOutScore) -> str:
    """The champion's held-out test, the figures to quote about it."""
    worlds = [
        f"{label}: {_interval('roaming', w.roaming)}, {_interval('stuck', w.stuck)}"
        for label, w in (("under the reality gap", test.gap), ("nominal", test.nominal))
    ]
    return f"held-out test on {test.poses} unseen poses x {test.steps} steps (95 % CI), " + (
        "; ".join(worlds)
    )


def champion_lines(
    sha256: str,
    fitness: float | None,
    validation: ValidationScore | None,
    test: HeldOutScore | None,
) -> list[str]:
    """A champion in two lines: how it was chosen, then its held-out test (if it had one)."""
    lines = [f"champion {sha256[:SHORT_SHA]}: {chosen(fitness, validation)}"]
    if test is not None:
        lines.append(held_out(test))
    return lines


def _test(champion: dict[str, Any]) -> HeldOutScore | None:
    from schemas.run import HeldOutScore

    test = champion.get("test")
    return None if test is None else HeldOutScore.model_validate(test)


def run_champion_lines(run: dict[str, Any]) -> list[str]:
    """A RunOut's champion lines, or one line saying why it has none."""
    from schemas.run import ValidationScore

    c = run.get("champion")
    if c is not None:
        validation = c.get("validation")
        return champion_lines(
            c["sha256"],
            c.get("training_fitness"),
            None if validation is None else ValidationScore.model_validate(validation),
            _test(c),
        )
    if run["status"] == "failed":
        return ["no champion: the run failed before choosing one"]
    if run["status"] == "cancelled":
        return ["no champion: the run was cancelled before choosing one"]
    return ["no champion yet: a run chooses its champion once its last generation is evolved"]


def held_out_cells(champion: dict[str, Any] | None) -> tuple[str, str, str]:
    """(short sha, roaming, stuck) of a RunOut's champion for a table: each figure of its
    held-out test as "nominal / under the gap"; "-" where there is none."""
    if champion is None:
        return "-", "-", "-"
    sha = str(champion["sha256"])[:SHORT_SHA]
    t = _test(champion)
    if t is None:
        return sha, "-", "-"
    return (
        sha,
        f"{t.nominal.roaming.value:.0%} / {t.gap.roaming.value:.0%}",
        f"{t.nominal.stuck.value:.0%} / {t.gap.stuck.value:.0%}",
    )
