"""The cut-in scenario, one package: its parameters, names, controller and rule
(:mod:`~pemviz.scenarios.cut_in.scenario`, whose names this package re-exports), the geometry of each step
(:mod:`~pemviz.scenarios.cut_in.scene`), the tracker it builds on (:mod:`pemviz.stack.tracker`, scene-neutral), the
simulator on highway-env vehicles (:mod:`~pemviz.scenarios.cut_in.highway`), its batched twin
(:mod:`~pemviz.scenarios.cut_in.batched`), its problem (:mod:`~pemviz.scenarios.cut_in.problem`), a rollout's story
(:mod:`~pemviz.scenarios.cut_in.story`) and its drawing (:mod:`~pemviz.scenarios.cut_in.drawing`, with
:mod:`~pemviz.scenarios.cut_in.recording` and :mod:`~pemviz.scenarios.cut_in.panel`). Importing the package loads the
scenario module (and the tracker's parameters) only."""

from pemviz.scenarios.cut_in.scenario import (  # noqa: F401 (re-exported: importable from here as before)
    DEFAULT_TRAFFIC as DEFAULT_TRAFFIC,
    EGO_LANE as EGO_LANE,
    FAILURE_FORMULA as FAILURE_FORMULA,
    LANE_WIDTH_M as LANE_WIDTH_M,
    MAX_STEPS as MAX_STEPS,
    MONTE_CARLO_REFERENCE as MONTE_CARLO_REFERENCE,
    NO_VEHICLE_M as NO_VEHICLE_M,
    N_LANES as N_LANES,
    OBJECT_NAMES as OBJECT_NAMES,
    OBSERVATION_NAMES as OBSERVATION_NAMES,
    RARITY_SETTINGS as RARITY_SETTINGS,
    ROAD_LENGTH_M as ROAD_LENGTH_M,
    SALIENT_COLUMNS as SALIENT_COLUMNS,
    SALIENT_NAMES as SALIENT_NAMES,
    CutInParams as CutInParams,
    IDMParams as IDMParams,
    OtherVehicle as OtherVehicle,
    acc_control as acc_control,
    idm_acceleration as idm_acceleration,
    safe_distance as safe_distance,
)
