"""Pass criteria: one comparison each, parsed (never evaluated as code), judged against a run's facts."""

from __future__ import annotations

import pytest

from hilsim.campaign.criteria import CriterionError, evaluate, judge, parse

FACTS = {
    "exit_code": 0, "timed_out": False, "wall_s": 12.5,
    "summary": {"success": True, "failure": None, "duration_s": 25.7, "phases": [{"name": "dive"}],
                "thrusters": {"command": "duty"}},
    "bridge": {"late_ticks": 3, "contacts": {"count": 0}},
    "truth": {"contacts": 0, "max_depth_error_m": 0.012},
}


@pytest.mark.parametrize("text, ok", [
    ("exit_code == 0", True),
    ("exit_code != 0", False),
    ("0 == exit_code", True),
    ("summary.success == true", True),
    ("summary.success == 1", False),            # true is not 1
    ("summary.failure == null", True),
    ("summary.duration_s <= 25.7", True),
    ("summary.duration_s < 25.7", False),
    ("truth.max_depth_error_m < 1e-1", True),
    ("truth.max_depth_error_m > .02", False),
    ("bridge.contacts.count == 0", True),
    ("bridge.late_ticks >= -1", True),
    ("summary.phases.0.name == 'dive'", True),
    ('summary.thrusters.command == "rpm"', False),
    ("wall_s<13", True),
    ("timed_out == false", True),
])
def test_comparisons_follow_their_operator(text: str, ok: bool) -> None:
    v = evaluate(parse(text), FACTS)
    assert v.ok is ok, v.detail


def test_a_missing_name_fails_and_says_so() -> None:
    v = evaluate(parse("summary.sonar.hold.frames > 3", "hold"), FACTS)
    assert not v.ok and v.detail == "summary.sonar.hold.frames missing"


def test_values_that_cannot_be_ordered_fail() -> None:
    v = evaluate(parse("summary.thrusters.command < 3"), FACTS)
    assert not v.ok and "cannot compare" in v.detail


def test_judge_names_the_first_failing_criterion() -> None:
    cs = [parse("exit_code == 0", "exit"), parse("truth.contacts == 0", "no_contact"),
          parse("truth.max_depth_error_m < 0.01", "depth"), parse("wall_s < 1", "quick")]
    ok, bad = judge(cs, FACTS)
    assert not ok and bad is not None and bad.criterion.name == "depth"
    assert "truth.max_depth_error_m = 0.012" in bad.detail


@pytest.mark.parametrize("text, why", [
    ("__import__('os').system('true')", "unexpected"),
    ("exit_code == 0 and wall_s < 5", "unexpected 'and'"),
    ("exit_code == 0 == 0", "more than one comparison"),
    ("exit_code + 1 == 1", "unexpected '+"),
    ("len(summary.phases) > 2", "unexpected '(summary"),
    ("summary.success", "no comparison operator"),
    ("exit_code = 0", "unexpected '= 0' at column 11"),
    ("os.system == 0", "unknown name 'os.system'"),
    ("summary == 0", "needs a field"),
    ("1 < 2", "compares two constants"),
    ("", "expected a comparison"),
    ("exit_code == ", "incomplete comparison"),
    ("exit_code == [0]", "unexpected '[0]' at column 14"),
])
def test_anything_but_one_comparison_is_refused(text: str, why: str) -> None:
    with pytest.raises(CriterionError) as e:
        parse(text)
    assert why in str(e.value), str(e.value)
