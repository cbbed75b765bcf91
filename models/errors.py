"""Errors the science raises for input a person can correct."""


class InputError(ValueError):
    """The data or settings given cannot be used; the message says why and what to do."""
