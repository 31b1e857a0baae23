"""The validation suite: subjects whose truth another FE code computed, run through the whole
pipeline as a user would, with every stage's figure per subject.

Each subject is run in two *arms*:

``pipeline``
    everything as a user would run it: the project's segmentation, registration, meshing,
    fit of one breast modulus on the calibration positions, prediction of every position;
``truth_labels``
    the same with the truth label maps given (``[segment] labels``), which takes the
    segmentation out of the question and separates the stages;
``reference_truth`` (on request)
    the truth label map of the reference position alone (the mesh is built from it), the
    other positions segmented: which of the two segmentations a miss comes from.

A stage that stops is recorded with its error (the figures of the stages before it are
kept); it never stops the suite. :data:`TARGETS` lists the figures the open issues target:
each is checked and recorded; the enforced ones fail a test when missed.
"""

from breastmodel.validation.figures import arm_figures, chest_wall_points
from breastmodel.validation.suite import (
    evaluate_subject,
    family_maker,
    run_arm,
    run_suite,
    split_positions,
    suite_config,
)
from breastmodel.validation.tables import format_table, summary_rows
from breastmodel.validation.targets import (
    ARMS,
    EXTRA_ARMS,
    FIT_PARAMETER,
    TARGETS,
    Target,
    check_targets,
)

__all__ = ["ARMS", "EXTRA_ARMS", "FIT_PARAMETER", "TARGETS", "Target", "arm_figures",
           "check_targets", "chest_wall_points", "evaluate_subject", "family_maker",
           "format_table", "run_arm", "run_suite", "split_positions", "suite_config",
           "summary_rows"]
