"""JSON request bodies parsed strictly: numbers the engine cannot hold are 422, not 500.

Python's ``json`` module reads integers of any size (and refuses, with a ``ValueError``
FastAPI does not expect, those over 4300 digits), reads ``1e400`` as infinity and
accepts ``NaN``/``Infinity``, which are not JSON at all. A number like that, anywhere in
a body, would reach a database column or a torch tensor and fail there. Every route of
the API is a :class:`StrictJsonRoute`, whose request parses JSON with :func:`loads`:

* an integer outside the signed 64-bit range, a float that overflows a double, and
  ``NaN``/``Infinity``/``-Infinity`` answer **422** ``validation-error`` naming the
  field (``body.config.iterations``), before any route code runs;
* nesting deeper than the parser's recursion limit, and bytes that are not text, answer
  400 ``malformed-json``.
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Callable, Coroutine, Iterator
from typing import Any

from fastapi import Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute

INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1
_INT64_DIGITS = len(str(INT64_MAX))


class _Refused:
    """A number the API does not accept, left in place so its path can be reported."""

    __slots__ = ("message", "text")

    def __init__(self, text: str, message: str) -> None:
        self.text = text if len(text) <= 40 else text[:37] + "..."
        self.message = message


def _parse_int(text: str) -> int | _Refused:
    # the length first: int() of a 5000-digit string raises ValueError in Python 3.11+
    if len(text.lstrip("-")) > _INT64_DIGITS or not INT64_MIN <= int(text) <= INT64_MAX:
        return _Refused(text, "integer out of range: numbers must fit a signed 64-bit integer")
    return int(text)


def _parse_float(text: str) -> float | _Refused:
    value = float(text)
    if not math.isfinite(value):
        return _Refused(text, "number out of range: it overflows a double")
    return value


def _parse_constant(name: str) -> _Refused:
    return _Refused(name, f"{name} is not a JSON number (NaN and Infinity are refused)")


def _refused(data: Any) -> Iterator[tuple[tuple[Any, ...], _Refused]]:
    """(location, refusal) of every refused number in a parsed body (iterative walk)."""
    stack: list[tuple[tuple[Any, ...], Any]] = [(("body",), data)]
    while stack:
        loc, value = stack.pop()
        if isinstance(value, _Refused):
            yield loc, value
        elif isinstance(value, dict):
            stack.extend(((*loc, k), v) for k, v in reversed(value.items()))
        elif isinstance(value, list):
            stack.extend(((*loc, i), v) for i, v in reversed(list(enumerate(value))))


def loads(body: bytes | str) -> Any:
    """Parse a request body; :class:`RequestValidationError` naming every refused number."""
    try:
        data = json.loads(
            body,
            parse_int=_parse_int,
            parse_float=_parse_float,
            parse_constant=_parse_constant,
        )
    except RecursionError:
        raise json.JSONDecodeError("nested too deeply", "", 0) from None
    except UnicodeDecodeError:  # a ValueError FastAPI would answer with a bare 400
        raise json.JSONDecodeError("not UTF-8 (or UTF-16/32) text", "", 0) from None
    errors = [
        {
            "type": "number_out_of_range",
            "loc": loc,
            "msg": f"{bad.message} (got {bad.text})",
            "input": bad.text,
        }
        for loc, bad in _refused(data)
    ]
    if errors:
        raise RequestValidationError(errors)
    return data


class StrictJsonRequest(Request):
    """A request whose ``json()`` is :func:`loads` (cached like Starlette's)."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            self._json = loads(await self.body())
        return self._json


class StrictJsonRoute(APIRoute):
    """The route class of every API router: its handler sees a :class:`StrictJsonRequest`."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        takes_json = self.body_field is not None  # streamed uploads declare no body field

        async def strict(request: Request) -> Response:
            req = StrictJsonRequest(request.scope, request.receive)
            if takes_json and _json_content(req):
                # parsed here, before FastAPI's handler, which turns any error other than
                # a syntax error into a bare 400; a syntax error is left to it (400
                # malformed-json), since a failed parse is not cached
                with contextlib.suppress(json.JSONDecodeError):
                    await req.json()
            return await handler(req)

        return strict


def _json_content(request: Request) -> bool:
    """Whether FastAPI would parse this body as JSON (no content type, or ``*/json``)."""
    ctype = request.headers.get("content-type")
    if ctype is None:
        return True
    main, _, sub = ctype.split(";")[0].strip().lower().partition("/")
    return main == "application" and (sub == "json" or sub.endswith("+json"))
