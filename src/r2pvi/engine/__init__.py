"""The one backward-induction engine shared by every algorithm (Algorithms 1-2 of the paper).

- :mod:`~r2pvi.engine.induction` — the loop over steps ``h = H-1, ..., 0``
  (:func:`backward_induction`) and the interface an algorithm implements (:class:`StepRule`);
- :mod:`~r2pvi.engine.steps` — how a step's rows reach its ridge operator (by chunk:
  :class:`ChunkedRidgeExpectation`; whole; pooled over the steps: :func:`pooled_steps`);
- :mod:`~r2pvi.engine.penalty` — the pessimism penalty ``Gamma_h`` (:func:`penalty_values`);
- :mod:`~r2pvi.engine.q` — the fitted model and ``Q_h`` from it (:func:`q_values_from_model`).

Imports point one way: ``induction`` -> ``steps``, ``q`` -> ``penalty``.
"""

from .induction import StepContext, StepRule, backward_induction
from .penalty import PENALTIES, elliptical_norms, penalty_values
from .q import FittedModel, q_values_from_model
from .steps import ChunkedRidgeExpectation, pooled_steps

__all__ = [
    "StepRule",
    "StepContext",
    "ChunkedRidgeExpectation",
    "FittedModel",
    "backward_induction",
    "penalty_values",
    "elliptical_norms",
    "q_values_from_model",
    "pooled_steps",
    "PENALTIES",
]
