"""Theory in practice: the paper's beta, bounds and the instance-dependent uncertainty term."""

from .bounds import instance_independent_bound, theoretical_beta, xi

__all__ = ["theoretical_beta", "xi", "instance_independent_bound"]
