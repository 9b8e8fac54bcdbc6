"""Procedural 3DGS objects and random perturbations for tests, demo and benchmarks."""

from gsa.synth.objects import CATEGORIES, make_object
from gsa.synth.perturb import paper_perturbation, random_sim3

__all__ = ["CATEGORIES", "make_object", "paper_perturbation", "random_sim3"]
