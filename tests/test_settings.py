"""The settings mixin: every field checked against its declared rule, on every construction."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pytest

from relpoint.errors import UsageError
from relpoint.estimators import ESTIMATORS
from relpoint.estimators._fix_frame import FixFusionSettings
from relpoint.estimators._landmark_motion import MovingLandmarkSettings
from relpoint.estimators._noise import MotionNoiseSettings
from relpoint.estimators.dense.estimator import DenseConfig
from relpoint.estimators.ekf import EkfConfig
from relpoint.estimators.fastslam import FastSlamConfig
from relpoint.estimators.relative_point.config import RelativePointConfig
from relpoint.evaluation import AlignMode, EvaluationSettings
from relpoint.frontend.tracking import KeypointSettings
from relpoint.fusion.fuse import FusionConfig
from relpoint.settings import DEFAULT_FLOAT_LIMITS, Settings, split_item
from relpoint.simulation.config import SimulationConfig
from relpoint.simulation.rgbd import RgbdConfig
from relpoint_app.batch_plan import RunOptions

CLASSES = (
    RelativePointConfig, EkfConfig, FastSlamConfig, DenseConfig, FusionConfig, SimulationConfig, RgbdConfig,
    KeypointSettings, EvaluationSettings, RunOptions, MovingLandmarkSettings, FixFusionSettings, MotionNoiseSettings,
)  # fmt: skip
NUMERIC = ("int", "float", "int | None", "float | None", "tuple[int, ...]", "tuple[float, ...]")


def _subclasses(klass: type) -> set[type]:
    return {sub for direct in klass.__subclasses__() for sub in (direct, *_subclasses(direct))}


def _fields(klass: type) -> list[dataclasses.Field[Any]]:
    return list(dataclasses.fields(klass))


def _numeric_fields() -> list[tuple[type, str, str]]:
    return [(klass, f.name, str(f.type)) for klass in CLASSES for f in _fields(klass) if str(f.type) in NUMERIC]


def _outside(klass: type[Settings], name: str, annotation: str) -> list[Any]:
    """Values just outside field ``name``'s range (or not among its choices)."""
    rule = klass.field_rule(name)
    kind = "int" if "int" in annotation else "float"
    if rule.choices is not None:
        return [max(rule.choices) + 1]
    low, high, low_in, high_in = rule.bounds(kind)
    values = [low - 1 if low_in else low]
    if not (math.isinf(high) and high_in):
        values.append(high + 1 if high_in and kind == "int" else high * 2 if high_in else high)
    return values


def test_every_settings_class_is_covered() -> None:
    assert {klass for klass in _subclasses(Settings) if dataclasses.is_dataclass(klass)} <= set(CLASSES)


@pytest.mark.parametrize("klass", CLASSES, ids=lambda k: k.__name__)
def test_every_field_declares_a_check_unless_bool_or_other(klass: type[Settings]) -> None:
    for f in _fields(klass):
        annotation = str(f.type).replace(" | None", "")
        if annotation in ("int", "float", "str") or annotation.startswith("tuple["):
            assert klass.field_rule(f.name).declared, f"{klass.__name__}.{f.name} declares no range or choices"
        else:
            assert annotation == "bool" or annotation[0].isupper(), f"{klass.__name__}.{f.name}: {annotation}"


@pytest.mark.parametrize("klass", CLASSES, ids=lambda k: k.__name__)
def test_defaults_pass_their_own_checks(klass: type[Settings]) -> None:
    defaults = klass()
    assert klass.from_mapping(defaults.to_dict()) == defaults


@pytest.mark.parametrize(("klass", "name", "annotation"), _numeric_fields(), ids=lambda v: getattr(v, "__name__", v))
def test_a_bool_is_no_number_given_to_the_constructor(klass: type[Settings], name: str, annotation: str) -> None:
    value = (True,) * len(getattr(klass(), name)) if annotation.startswith("tuple") else True
    with pytest.raises(UsageError, match=rf"{klass.settings_name} setting {name}\b.*must be .*got True"):
        klass(**{name: value})


@pytest.mark.parametrize(("klass", "name", "annotation"), _numeric_fields(), ids=lambda v: getattr(v, "__name__", v))
def test_out_of_range_values_given_to_the_constructor_are_usage_errors(
    klass: type[Settings], name: str, annotation: str
) -> None:
    for bad in _outside(klass, name, annotation):
        value = (bad,) * len(getattr(klass(), name)) if annotation.startswith("tuple") else bad
        with pytest.raises(UsageError) as caught:
            klass(**{name: value})
        message = str(caught.value)
        assert name in message and "must be" in message and "got" in message and "\n" not in message


@pytest.mark.parametrize("klass", CLASSES, ids=lambda k: k.__name__)
def test_text_outside_the_choices_and_nan_are_usage_errors(klass: type[Settings]) -> None:
    for f in _fields(klass):
        rule = klass.field_rule(f.name)
        if rule.choices is not None and all(isinstance(c, str) for c in rule.choices):
            with pytest.raises(UsageError, match=rf"{f.name} must be one of .*, got 'no-such-choice'"):
                klass(**{f.name: "no-such-choice"})
        if str(f.type) in ("float", "float | None"):
            with pytest.raises(UsageError, match=rf"{f.name} must be a finite number .*got nan"):
                klass(**{f.name: math.nan})


@pytest.mark.parametrize("klass", CLASSES, ids=lambda k: k.__name__)
def test_unknown_keys_are_named_with_the_class_hint(klass: type[Settings]) -> None:
    hint = klass.settings_hint or "known settings are " + ", ".join(sorted(f.name for f in _fields(klass)))
    for build in (lambda: klass.from_mapping({"no_such_key": 1}), lambda: klass.from_strings(["no_such_key=1"])):
        with pytest.raises(UsageError) as caught:
            build()
        assert caught.value.message == f"unknown {klass.settings_name} setting(s): no_such_key"
        assert caught.value.hint == hint


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
def test_estimator_parameters_are_checked_by_their_config_class(name: str) -> None:
    spec = ESTIMATORS[name]
    assert spec.config_class.settings_hint == f"see `relpoint config --estimator {name}` for the parameters"
    with pytest.raises(UsageError) as caught:
        spec.build_config({"bad_b": 1}, ["bad_a=2"])
    assert caught.value.message == f"unknown {name} setting(s): bad_a, bad_b"
    assert spec.build_config({}, []) == spec.config_class()


def test_cross_field_rules_run_after_the_field_checks() -> None:
    for build, words in (
        (lambda: RelativePointConfig(match_window=200), "match_window"),
        (lambda: EkfConfig(gate_probability=0.999, new_landmark_probability=0.99), "new_landmark_probability"),
        (lambda: FastSlamConfig(start_landmark_probability=0.99), "start_landmark_probability"),
        (lambda: DenseConfig(pyramid_levels=2), "icp_iterations"),
        (lambda: DenseConfig(min_depth=5.0, max_depth=4.0), "min_depth"),
        (lambda: FusionConfig(local_sigma=0.0, drift_fraction=0.0), "local_sigma"),
        (lambda: SimulationConfig(min_range=80.0), "min_range"),
        (lambda: RgbdConfig(min_range=6.0), "min_range"),
        (lambda: KeypointSettings(min_depth=6.0), "min_depth"),
        (lambda: EvaluationSettings(delta=1.5), "delta"),
    ):
        with pytest.raises(UsageError, match=words):
            build()
    # A bad value is reported by its own field before any rule that relates it to others.
    with pytest.raises(UsageError, match="ring_size must be between 1 and 65536, got 0"):
        RelativePointConfig(ring_size=0)


def test_ranges_open_and_closed() -> None:
    assert EvaluationSettings(n_to_align=-1).n_to_align == -1  # -1 (all poses) besides the range
    with pytest.raises(UsageError, match="n_to_align must be -1 or between 1 and 1e\\+09, got 0"):
        EvaluationSettings(n_to_align=0)
    with pytest.raises(UsageError, match="gate_probability must be strictly between 0 and 1, got 1"):
        EkfConfig(gate_probability=1.0)
    with pytest.raises(UsageError, match="match_bound must be between 0 \\(excluded\\) and 1e\\+09, got 0"):
        RelativePointConfig(match_bound=0.0)
    assert FusionConfig(max_position_error=math.inf).max_position_error == math.inf  # inf = never
    with pytest.raises(UsageError, match="max_position_error must be above 0, got 0"):
        FusionConfig(max_position_error=0.0)
    with pytest.raises(UsageError, match="delta_tol must be a finite number at least 0, got inf"):
        EvaluationSettings(delta_tol=math.inf)
    with pytest.raises(UsageError, match="downsample must be one of 0, 1, 2, 4, got 3"):
        DenseConfig(downsample=3)
    with pytest.raises(UsageError, match=r"icp_iterations\[1\] must be an integer, got 2.5"):
        DenseConfig(icp_iterations=(1, 2.5, 3))  # type: ignore[arg-type]
    assert RunOptions(seed=2**70).seed == 2**70  # a seed has no upper bound
    with pytest.raises(UsageError, match="run setting seed must be at least 0, got -1"):
        RunOptions(seed=-1)
    with pytest.raises(UsageError, match=r"ekf setting observation_sigma must be between 1e-06 and 1000, got 0.0"):
        EkfConfig(observation_sigma=0.0)
    with pytest.raises(UsageError, match=r"simulation setting passes must be an integer, got 2.0"):
        SimulationConfig(passes=2.0)  # type: ignore[arg-type]
    with pytest.raises(UsageError, match="fusion setting min_matches needs a value"):
        FusionConfig(min_matches=None)  # type: ignore[arg-type]


def test_limits_and_ranges_as_relpoint_config_shows_them() -> None:
    assert EkfConfig.field_limits("observation_sigma") == (1e-6, 1e3)
    assert RelativePointConfig.field_limits("match_bound") == (0, DEFAULT_FLOAT_LIMITS[1])
    assert EkfConfig.field_limits("association") is None and DenseConfig.field_limits("downsample") is None
    assert DenseConfig.field_limits("icp_iterations") == (0, 1_000_000)
    assert EkfConfig.field_range("gate_probability") == "(0 .. 1)"
    assert EkfConfig.field_range("association") == "{nn, jcbb, known}"
    assert EvaluationSettings.field_range("n_to_align") == "-1 or [1 .. 1e+09]"
    assert EkfConfig.field_range("rigid_consensus") is None


def test_values_given_directly_are_normalised_before_the_checks() -> None:
    settings = EvaluationSettings(align="SE3", kitti_lengths=[100, 200])  # type: ignore[arg-type]
    assert settings.align is AlignMode.SE3 and settings.kitti_lengths == (100.0, 200.0)
    assert DenseConfig(icp_iterations=[3, 4, 5]).icp_iterations == (3, 4, 5)  # type: ignore[arg-type]
    assert EkfConfig(position_noise=1).position_noise == 1  # an int is a number


def test_a_digit_separator_is_no_number_on_the_command_line() -> None:
    # Python reads int("1_0") and float("1_0") as 10: a typo of 1.0 or 10 silently became 10.
    for item in ("fix_gate_patience=1_0", "fix_gate_probability=0.9_9", "icp_iterations=2,1_0"):
        klass = DenseConfig if item.startswith("icp") else EkfConfig
        with pytest.raises(UsageError, match="must be"):
            klass.from_strings([item])
    assert EkfConfig.from_strings(["fix_gate_patience=10"]).fix_gate_patience == 10


def test_from_mapping_and_from_strings_read_each_value_as_its_kind() -> None:
    config = DenseConfig.from_strings(["icp_iterations=(2, 3)", "pyramid-levels=2", "map_normals=yes"])
    assert config.icp_iterations == (2, 3) and config.pyramid_levels == 2 and config.map_normals is True
    assert DenseConfig.from_mapping({"icp_iterations": [4.0, 5, 10]}).icp_iterations == (4, 5, 10)
    assert FusionConfig.from_strings(["max_position_error=inf"]).max_position_error == math.inf
    assert EkfConfig.from_strings(["observation_sigma=none"], base={"observation_sigma": 0.5}).observation_sigma is None
    assert isinstance(EkfConfig.from_mapping({"position_noise": 1}).position_noise, float)
    assert FastSlamConfig.from_mapping({"variant": 1.0}).variant == "1.0"
    with pytest.raises(UsageError, match=r"ring_size must be an integer, got 2.5"):
        RelativePointConfig.from_mapping({"ring_size": 2.5})
    with pytest.raises(UsageError, match="icp_iterations must be comma-separated numbers"):
        DenseConfig.from_strings(["icp_iterations=a,b"])
    with pytest.raises(UsageError, match=r"evaluation setting align must be one of none, se3, .*, got 'banana'"):
        EvaluationSettings.from_mapping({"align": "banana"})
    with pytest.raises(UsageError, match=r"pose_relation must be one of .*, got 'point_distance_error_ratio'"):
        EvaluationSettings.from_mapping({"pose_relation": "point_distance_error_ratio"})


def test_key_value_items_are_split_in_one_place() -> None:
    assert split_item(" a-b = 3 ") == ("a-b", " 3 ")
    for bad in ("no_equals", "=3", " =3"):
        with pytest.raises(UsageError, match=r"--param .* is not KEY=VALUE"):
            split_item(bad)
        with pytest.raises(UsageError, match="is not KEY=VALUE"):
            EkfConfig.from_strings([bad])
    with pytest.raises(UsageError, match="--fail-above 'x' is not KEY=VALUE"):
        split_item("x", "--fail-above")


def test_the_scene_folds_the_scale_into_every_length() -> None:
    config = SimulationConfig(scale=0.1, density=400.0)
    scene = config.scene()
    assert scene.step == 1.2 * 0.1 and scene.range == 70.0 * 0.1 and scene.radius == 95.0 * 0.1
    assert scene.density == 400.0 / 0.1 and scene.scale == 1.0 and scene.noise == config.noise
    # A folded value may lie beyond what a user may set: the scene is no SimulationConfig.
    assert SimulationConfig(scale=1e-3, density=1e4).scene().density == pytest.approx(1e7)
