"""A run's step reports are counted by how their line search ended, and the counts say when the result is wrong."""

from pienerf.scenario import StepTally
from pienerf.sim.solver import QGMLSStepReport


def _tally(*reports: QGMLSStepReport) -> StepTally:
    tally = StepTally()
    for report in reports:
        tally.add(report)
    return tally


def test_converged_steps_leave_nothing_to_report():
    tally = _tally(QGMLSStepReport(iterations=3, converged=True), QGMLSStepReport(iterations=2, converged=True))
    assert tally.to_dict() == {
        "steps": 2,
        "unconverged_steps": 0,
        "line_search_failed_steps": 0,
        "line_search_failures": {},
        "stuck_steps": 0,
        "wrong_result": None,
    }


def test_a_single_not_finite_line_search_makes_the_result_wrong():
    tally = _tally(
        QGMLSStepReport(iterations=4, converged=True), QGMLSStepReport(iterations=3, line_search_failure="not finite")
    )
    assert tally.line_search_failures == {"not finite": 1} and tally.unconverged == 1
    assert tally.wrong_result() == "1 of 2 steps met non-finite values (NaN) in their line search"


def test_inversions_after_progress_are_counted_but_not_wrong():
    tally = _tally(
        QGMLSStepReport(iterations=5, line_search_failure="inversion"),
        QGMLSStepReport(iterations=1, line_search_failure="inversion"),
        QGMLSStepReport(iterations=2, line_search_failure="no decrease"),
    )
    assert tally.failed == 3 and tally.stuck == 1
    assert tally.line_search_failures == {"inversion": 2, "no decrease": 1}
    assert tally.wrong_result() is None


def test_a_run_whose_every_step_is_stuck_is_wrong():
    tally = _tally(*[QGMLSStepReport(iterations=1, line_search_failure="inversion")] * 3)
    assert tally.wrong_result() == "the line search could not move the body in any of the 3 steps"
    assert StepTally().wrong_result() is None  # no steps: nothing went wrong
