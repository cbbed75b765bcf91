"""Option groups: options that several ``narxwatch-sim`` commands take, declared once as the
fields of a dataclass and spread into each command's signature by :func:`expanded`."""

from __future__ import annotations

import dataclasses
import functools
import inspect
import typing
from collections.abc import Callable
from typing import Any

KEYWORD_ONLY = inspect.Parameter.KEYWORD_ONLY


def expanded(command: Callable[..., None]) -> Callable[..., None]:
    """``command`` with each parameter annotated by an option group (a dataclass whose fields are
    annotated options with defaults) replaced by the group's fields, in their order and where the
    parameter stood; it is called with the group built from them. Typer reads the signature."""
    hints = typing.get_type_hints(command, include_extras=True)
    groups: dict[str, type] = {}
    parameters = []
    for parameter in inspect.signature(command).parameters.values():
        kind = hints[parameter.name]
        if not (isinstance(kind, type) and dataclasses.is_dataclass(kind)):
            parameters.append(parameter.replace(annotation=kind, kind=KEYWORD_ONLY))
            continue
        groups[parameter.name] = kind
        fields = typing.get_type_hints(kind, include_extras=True)
        parameters += [
            inspect.Parameter(field.name, KEYWORD_ONLY, annotation=fields[field.name], default=field.default)
            for field in dataclasses.fields(kind)
        ]

    @functools.wraps(command)
    def run(**given: Any) -> None:
        for name, group in groups.items():
            given[name] = group(**{field.name: given.pop(field.name) for field in dataclasses.fields(group)})
        command(**given)

    run.__signature__ = inspect.Signature(parameters)  # type: ignore[attr-defined]
    run.__annotations__ = {parameter.name: parameter.annotation for parameter in parameters}
    return run
