"""The automated-braking scenario of Innes & Ramamoorthy (2022), one package: the simulator on highway-env vehicles
and its parameters (:mod:`~pemviz.scenarios.braking.simulator`, whose names this package re-exports), its batched
twin (:mod:`~pemviz.scenarios.braking.batched`), its problem (:mod:`~pemviz.scenarios.braking.problem`), its exact
answers (:mod:`~pemviz.scenarios.braking.truth`, with :mod:`~pemviz.scenarios.braking.truth_latched` and
:mod:`~pemviz.scenarios.braking.truth_known`), a failure's story (:mod:`~pemviz.scenarios.braking.failures`) and its
drawing (:mod:`~pemviz.scenarios.braking.drawing`, with :mod:`~pemviz.scenarios.braking.recording` and
:mod:`~pemviz.scenarios.braking.panel`). Importing the package loads the simulator module only."""

from pemviz.scenarios.braking.simulator import (  # noqa: F401 (re-exported: importable from here as before)
    BRAKING_SIGNAL_RANGES as BRAKING_SIGNAL_RANGES,
    BRAKING_SIGNALS as BRAKING_SIGNALS,
    BRAKING_UNITS as BRAKING_UNITS,
    LEAD_SPEED_PROFILE_MPS as LEAD_SPEED_PROFILE_MPS,
    OBSERVATION_NAMES as OBSERVATION_NAMES,
    BrakingParams as BrakingParams,
    BrakingScenario as BrakingScenario,
    ControllerState as ControllerState,
    braking_replay as braking_replay,
    braking_step as braking_step,
    ego_acceleration as ego_acceleration,
    ego_step as ego_step,
    initial_controller_state as initial_controller_state,
    lead_speeds as lead_speeds,
)
