"""Errors jaxland raises: each names what was wrong, the value, and the rule."""

from __future__ import annotations


class JaxlandError(Exception):
    """Base class of jaxland's errors."""


class ConfigError(JaxlandError, ValueError):
    """A parameter, scene or solver value breaks its rule."""

    def __init__(self, field: str, value, rule: str):
        if hasattr(value, "item") and getattr(value, "ndim", 1) == 0:
            value = value.item()  # numpy scalar -> plain Python number in the message
        self.field, self.value, self.rule = field, value, rule
        super().__init__(f"{field} = {value!r}: {rule}")


class SimulationError(JaxlandError, RuntimeError):
    """A landing's answer is not to be used (``jaxland.Result``'s failure codes): the state
    turned non-finite, the energy ledger grew or did not close, the step was above the limit
    of the forces reached, or an adaptive solver stopped; the message says what to change."""
