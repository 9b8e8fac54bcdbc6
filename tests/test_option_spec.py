"""gsa.align.spec.OPTIONS, the one description of the alignment options: it covers
AlignOptions' fields, agrees with their types and defaults, and the CLI, AlignOptions' checks and
the service's model of the options are made from it."""

from __future__ import annotations

import argparse
import dataclasses
import typing

import pytest

from gsa.align.pipeline import AlignOptions
from gsa.align.spec import OPTIONS, Bound, choice_error


def _literal_args(tp) -> tuple:
    """The Literal values of a field type (through `X | None` and tuple[X, ...])."""
    out: tuple = ()
    for arg in typing.get_args(tp) or ():
        out += _literal_args(arg) if typing.get_origin(arg) is not None else ()
    return typing.get_args(tp) if typing.get_origin(tp) is typing.Literal else out


def test_every_field_is_described_once():
    assert list(OPTIONS) == [f.name for f in dataclasses.fields(AlignOptions)]
    assert all(spec.help for spec in OPTIONS.values())


def test_the_spec_agrees_with_the_fields():
    hints = typing.get_type_hints(AlignOptions)
    defaults = AlignOptions()
    for name, spec in OPTIONS.items():
        default = getattr(defaults, name)
        if spec.kind == "choice":
            assert set(spec.choices) == set(_literal_args(hints[name])), name
            assert default in spec.choices
        if spec.kind in ("int", "float", "bool"):
            kind = {"int": int, "float": float, "bool": bool}[spec.kind]
            assert kind in (hints[name], *typing.get_args(hints[name])), name
        for bound in (spec.bounds, spec.limits):
            if bound is not None and default is not None:
                assert bound.contains(default), name
        if spec.bounds is not None and spec.limits is not None:  # a job's range within the library's
            lo, hi = spec.limits.lo, spec.limits.hi
            assert spec.bounds.contains(lo if not spec.limits.lo_open else lo + 1e-9), name
            assert hi is None or spec.bounds.contains(hi), name


def test_align_options_checks_come_from_the_spec():
    with pytest.raises(ValueError, match="search must be auto, global or frames, got 'x'"):
        AlignOptions(search="x")
    with pytest.raises(ValueError, match="features must be one of auto, file, canonical, spheremap, dinov2"):
        AlignOptions(features="x")
    with pytest.raises(ValueError, match="fine_loss must be smooth_l1, l1 or l2"):  # before the fine stage
        AlignOptions(fine_loss="l7")
    with pytest.raises(ValueError, match="tau_f must be positive"):
        AlignOptions(tau_f=0)
    with pytest.raises(ValueError, match="coarse_iterations must be at least 1"):
        AlignOptions(coarse_iterations=0)
    with pytest.raises(ValueError, match=r"anchor_count must be in 100\.\.20000"):
        AlignOptions(anchor_count=50)
    with pytest.raises(ValueError, match="weight_by_opacity must be true or false"):
        AlignOptions(weight_by_opacity=1)
    AlignOptions(trim=None, max_candidates=1000, hypothesis_points=5)  # the service's limits are not the library's


def test_choice_error_wording():
    assert choice_error("semantic", ("auto", "off"), "x") == "semantic must be auto or off, got 'x'"
    assert Bound(int, 1, 1000).describe() == "an integer in [1, 1000]"
    assert Bound(float, 0, None, lo_open=True).describe() == "a number > 0"


def test_cli_flags_are_made_from_the_spec():
    from gsa.align.command import CLI_GUIDANCE_OPTIONS, CLI_OPTIONS, _align_options, add_align_arguments

    with_flag = {name for name, spec in OPTIONS.items() if spec.cli is not None}
    assert with_flag == {"stages", "features", *CLI_OPTIONS, *CLI_GUIDANCE_OPTIONS}
    parser = argparse.ArgumentParser()
    add_align_arguments(parser)
    actions = {a.dest: a for a in parser._actions}
    assert actions["iterations"].default == AlignOptions().coarse_iterations
    assert actions["iterations"].help == OPTIONS["coarse_iterations"].help
    assert tuple(actions["refine"].choices) == OPTIONS["refine"].choices
    assert actions["scale"].metavar == "S" and actions["fine_views"].default is None
    opts = _align_options(parser.parse_args(["--iterations", "7", "--scale", "2", "--fine-on", "colors"]))
    assert (opts.coarse_iterations, opts.fixed_scale, opts.fine_on) == (7, 2.0, "colors")
    assert opts.fine_views == AlignOptions().fine_views  # unset: the library's default


def test_the_service_model_is_made_from_the_spec():
    pytest.importorskip("pydantic")
    from service.jobs.options import OPTION_BOUNDS, OPTION_CHOICES, AlignOptionsIn, client_option_names

    props = AlignOptionsIn.model_json_schema()["properties"]
    # feature_settings: the deployment's; criteria: the library caller's
    assert set(client_option_names()) == set(OPTIONS) - {"feature_settings", "criteria"}
    for name in client_option_names():
        spec = OPTIONS[name]
        assert props[name]["description"].startswith(spec.help), name
        if spec.job_bounds is not None:
            assert OPTION_BOUNDS[name] == spec.job_bounds
            for key, value in spec.job_bounds.json_schema().items():
                assert props[name][key] == value, name
        if spec.kind == "choice":
            assert OPTION_CHOICES[name] == spec.choices
            assert props[name]["anyOf"][0]["enum"] == list(spec.choices), name
