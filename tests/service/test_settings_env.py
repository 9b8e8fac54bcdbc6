"""One environment name per setting: the learned features' weights are GSA_FEATURES_BACKBONE /
GSA_FEATURES_HEAD for the service as for the `gsa` CLI; the older GSA_DINOV2_WEIGHTS /
GSA_SPHEREMAP_WEIGHTS still work, with a deprecation warning once per process. The feature
variables are read when the settings are, not by every job."""

from __future__ import annotations

import logging

import pytest

from service import settings as settings_module
from service.settings import Settings


@pytest.fixture
def clean_env(monkeypatch):
    for var in ("GSA_FEATURES_BACKBONE", "GSA_FEATURES_HEAD", "GSA_DINOV2_WEIGHTS", "GSA_SPHEREMAP_WEIGHTS"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(settings_module, "_warned", set())
    return monkeypatch


def test_the_canonical_names_set_the_weights(clean_env):
    clean_env.setenv("GSA_FEATURES_BACKBONE", "/w/dinov2")
    clean_env.setenv("GSA_FEATURES_HEAD", "/w/head.pt")
    s = Settings()
    assert str(s.features_backbone) == "/w/dinov2" and str(s.features_head) == "/w/head.pt"
    assert s.feature_settings_kwargs()["backbone"] == "/w/dinov2"
    assert s.feature_settings_kwargs()["head"] == "/w/head.pt"


def test_the_deprecated_names_still_work_and_warn_once(clean_env, caplog):
    clean_env.setenv("GSA_DINOV2_WEIGHTS", "/w/old")
    clean_env.setenv("GSA_SPHEREMAP_WEIGHTS", "/w/old-head.pt")
    with caplog.at_level(logging.WARNING, logger="service.settings"):
        s = Settings()
        Settings()
    assert str(s.features_backbone) == "/w/old" and str(s.features_head) == "/w/old-head.pt"
    warnings = [r.getMessage() for r in caplog.records if "deprecated" in r.getMessage()]
    assert len(warnings) == 2, warnings
    assert any("GSA_DINOV2_WEIGHTS" in w and "GSA_FEATURES_BACKBONE" in w for w in warnings)


def test_the_canonical_name_wins_over_the_deprecated_one(clean_env):
    clean_env.setenv("GSA_DINOV2_WEIGHTS", "/w/old")
    clean_env.setenv("GSA_FEATURES_BACKBONE", "/w/new")
    assert str(Settings().features_backbone) == "/w/new"


def test_an_empty_variable_is_unset(clean_env):
    clean_env.setenv("GSA_FEATURES_HEAD", "")
    s = Settings()
    assert s.features_head is None and s.feature_settings_kwargs() is None


def test_feature_variables_are_read_with_the_settings_not_per_job(clean_env):
    clean_env.setenv("GSA_FEATURES_BACKBONE", "/w/dinov2")
    clean_env.setenv("GSA_LIFT_VIEWS", "7")
    s = Settings()
    clean_env.setenv("GSA_LIFT_VIEWS", "9")
    assert s.feature_settings_kwargs()["lift_views"] == 7
