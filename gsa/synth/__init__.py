"""Procedural 3DGS objects, furnished rooms (scenes) and random perturbations for tests, demo and benchmarks."""

from gsa.synth.objects import CATEGORIES, make_object
from gsa.synth.perturb import paper_perturbation, random_sim3
from gsa.synth.scenes import SceneCaptures, make_scene, scene_captures
from gsa.synth.variants import (
    SYMMETRIC_FAMILIES,
    add_floaters,
    cut_by_plane,
    deform,
    make_symmetric_object,
    random_exposure,
    shift_exposure,
    symmetric_spec,
    symmetry_rotations,
)

__all__ = [
    "CATEGORIES",
    "SYMMETRIC_FAMILIES",
    "SceneCaptures",
    "add_floaters",
    "cut_by_plane",
    "deform",
    "make_object",
    "make_scene",
    "make_symmetric_object",
    "paper_perturbation",
    "random_exposure",
    "random_sim3",
    "scene_captures",
    "shift_exposure",
    "symmetric_spec",
    "symmetry_rotations",
]
