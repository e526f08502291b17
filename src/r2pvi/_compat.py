"""scikit-learn compatibility without importing scikit-learn in the core.

scikit-learn only calls dunder methods on third-party estimators (``__sklearn_is_fitted__``,
``__sklearn_tags__``) and recognises unfitted estimators by its own ``NotFittedError``, which
derives from ``ValueError`` and ``AttributeError``. This module provides:

- :data:`NotFittedError` (resolved on first access): derives from ``ValueError`` and
  ``AttributeError`` and, when scikit-learn is installed, from
  ``sklearn.exceptions.NotFittedError`` too, so that ``check_is_fitted`` and
  ``pytest.raises(sklearn.exceptions.NotFittedError)`` recognise it;
- :class:`SklearnCompatMixin`: ``__sklearn_is_fitted__`` and a lazily built
  ``__sklearn_tags__`` (scikit-learn is imported inside the method, only when
  scikit-learn itself asks for the tags).

``import r2pvi`` never imports scikit-learn; the first access to ``NotFittedError`` (for
instance, raising it) does, when it is installed.
"""

from __future__ import annotations

import inspect

__all__ = ["SklearnCompatMixin", "not_fitted_error"]  # and NotFittedError, built lazily

_NOT_FITTED: type | None = None

_DOC = """Raised when an estimator is used before ``fit``.

Derives from ``ValueError`` and ``AttributeError`` (like scikit-learn's), and from
``sklearn.exceptions.NotFittedError`` when scikit-learn is installed.
"""


def not_fitted_error() -> type:
    """The ``NotFittedError`` class (built once, on first use; see the module docstring).

    Examples
    --------
    >>> import numpy as np
    >>> from r2pvi import PEVI, NotFittedError
    >>> try:
    ...     PEVI().act(np.ones((1, 2, 3)), 0)
    ... except NotFittedError as exc:
    ...     print(isinstance(exc, ValueError), isinstance(exc, AttributeError))
    True True
    """
    global _NOT_FITTED
    if _NOT_FITTED is None:
        bases: tuple[type, ...] = (ValueError, AttributeError)
        try:  # scikit-learn's class already derives from (ValueError, AttributeError)
            from sklearn.exceptions import NotFittedError as _SklearnNotFitted

            bases = (_SklearnNotFitted,)
        except Exception:  # not installed, or broken: the protocol alone
            pass
        _NOT_FITTED = type("NotFittedError", bases, {"__module__": "r2pvi", "__doc__": _DOC})
    return _NOT_FITTED


def __getattr__(name):
    if name == "NotFittedError":
        return not_fitted_error()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class SklearnCompatMixin:
    """``__sklearn_is_fitted__``, ``__sklearn_tags__`` and ``_repr_html_`` for the r2pvi
    estimators (the last two import scikit-learn when called).

    A subclass names the attribute that ``fit`` sets in ``_fitted_marker``.
    """

    _fitted_marker = "weights_"

    def __sklearn_is_fitted__(self) -> bool:
        return hasattr(self, self._fitted_marker)

    def _repr_html_(self):
        """The HTML repr of scikit-learn (notebooks) when it is installed, else None."""
        try:
            from sklearn.utils import estimator_html_repr
        except ImportError:
            return None
        return estimator_html_repr(self)

    def __sklearn_tags__(self):
        from sklearn.utils import InputTags, Tags, TargetTags

        # fit takes an OfflineDataset, not an (n, d) array X with a target y.
        return Tags(
            estimator_type=None,
            target_tags=TargetTags(required=False),
            input_tags=InputTags(two_d_array=False),
            requires_fit=True,
            non_deterministic=False,
        )


class KeywordParams:
    """scikit-learn's parameter protocol for classes whose ``__init__`` only stores its
    keyword parameters: ``get_params``/``set_params`` (validated at the next ``fit``)."""

    @classmethod
    def _param_names(cls) -> list[str]:
        sig = inspect.signature(cls.__init__)
        return [p.name for p in sig.parameters.values() if p.name != "self"]

    def get_params(self, deep: bool = True) -> dict:
        """The parameters as a dict (scikit-learn convention)."""
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params):
        """Set parameters by name and return ``self`` (validated at the next ``fit``)."""
        valid = self._param_names()
        for name, value in params.items():
            if name not in valid:
                raise ValueError(
                    f"invalid parameter {name!r} for {type(self).__name__}; valid: {valid}"
                )
            setattr(self, name, value)
        return self
