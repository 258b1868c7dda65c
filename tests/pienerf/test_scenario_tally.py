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
        "newton_tolerance_m": None,
        "newton_iterations_cap": None,
        "largest_unconverged_update_m": None,
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


def test_unconverged_steps_report_how_far_from_the_tolerance_they_ended():
    tally = StepTally(tolerance=1e-8, iteration_cap=50)
    for report in (
        QGMLSStepReport(iterations=50, last_update=3e-6),
        QGMLSStepReport(iterations=4, last_update=5e-9, converged=True),
        QGMLSStepReport(iterations=50, last_update=2e-7),
    ):
        tally.add(report)
    solver = tally.to_dict()
    assert solver["unconverged_steps"] == 2 and solver["largest_unconverged_update_m"] == 3e-6
    assert solver["newton_tolerance_m"] == 1e-8 and solver["newton_iterations_cap"] == 50
