"""Method calls as OPC UA answers: the inputs checked against the method's signature, and a refusal of the service
facade (an :class:`~tandemscan.daemon.api.errors.ApiProblem` or :class:`~tandemscan.daemon.jobs.manager.JobRequestError`
with its HTTP status) as a Bad status code with the problem's text (docs/opcua.md, methods).

A refusal answers the status code of its HTTP status (:data:`STATUS_OF_HTTP`) and the text in the method's
``Message`` output, so that a client sees why (OPC 10000-4 leaves the outputs of a Bad call empty; asyncua's
server offers no other place for a text).
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable, Sequence

from asyncua import ua
from pydantic import ValidationError
from tandemscan.daemon.api.errors import ApiProblem
from tandemscan.daemon.jobs.manager import JobRequestError

log = logging.getLogger(__name__)

#: OPC UA status of a refusal with this HTTP status
STATUS_OF_HTTP = {400: ua.StatusCodes.BadInvalidArgument, 401: ua.StatusCodes.BadUserAccessDenied,
                  404: ua.StatusCodes.BadNotFound, 409: ua.StatusCodes.BadInvalidState,
                  413: ua.StatusCodes.BadRequestTooLarge, 422: ua.StatusCodes.BadInvalidArgument,
                  507: ua.StatusCodes.BadResourceUnavailable}
#: longest string a text argument may be (the REST bodies' limit)
MAX_TEXT = 200


class CallRefused(Exception):
    """A call answered with ``status`` and ``text``."""

    def __init__(self, status: int, text: str):
        super().__init__(text)
        self.status, self.text = status, text


def result(status: int, outputs: Sequence[ua.Variant] = (), n_inputs: int = 0,
           input_results: Sequence[int] | None = None) -> ua.CallMethodResult:
    res = ua.CallMethodResult()
    res.StatusCode = ua.StatusCode(status)
    res.OutputArguments = list(outputs)
    res.InputArgumentResults = [ua.StatusCode(s) for s in (input_results or [ua.StatusCodes.Good] * n_inputs)]
    return res


def check_inputs(args: Sequence[ua.Variant], types: Sequence[ua.VariantType]) -> None:
    """Refuse (:class:`CallRefused`) arguments that do not match the signature: missing, too many, of another type
    or a text over :data:`MAX_TEXT` characters."""
    if len(args) < len(types):
        raise CallRefused(ua.StatusCodes.BadArgumentsMissing, f"{len(types)} arguments expected, {len(args)} given")
    if len(args) > len(types):
        raise CallRefused(ua.StatusCodes.BadTooManyArguments, f"{len(types)} arguments expected, {len(args)} given")
    for i, (arg, vt) in enumerate(zip(args, types, strict=True)):
        if not isinstance(arg, ua.Variant) or arg.VariantType != vt or arg.is_array:
            got = getattr(arg, "VariantType", type(arg).__name__)
            raise CallRefused(ua.StatusCodes.BadTypeMismatch, f"argument {i + 1} must be a {vt.name}, not {got}")
        if vt == ua.VariantType.String and arg.Value is not None and len(arg.Value) > MAX_TEXT:
            raise CallRefused(ua.StatusCodes.BadInvalidArgument, f"argument {i + 1} is over {MAX_TEXT} characters")


def checked_method(types: Sequence[ua.VariantType], action: Callable[..., Awaitable[list[ua.Variant]]],
                   refusal_outputs: Callable[[CallRefused], list[ua.Variant]]
                   ) -> Callable[..., Awaitable[ua.CallMethodResult]]:
    """A method callback: the inputs checked against ``types``, then ``action(*values)`` (its outputs); a refusal
    answers its status code, ``refusal_outputs(refusal)`` and the text in the log."""

    async def call(parent: ua.NodeId, *args: ua.Variant) -> ua.CallMethodResult:
        try:
            check_inputs(args, types)
            outputs = await refusals_as_calls(action, *(a.Value for a in args))
        except CallRefused as e:
            log.info("OPC UA call refused (%s): %s", ua.StatusCode(e.status).name, e.text)
            return result(e.status, refusal_outputs(e), len(args))
        return result(ua.StatusCodes.Good, outputs, len(args))

    return call


def spec_method(types: Sequence[ua.VariantType], action: Callable[..., Awaitable[list[ua.Variant]]]
                ) -> Callable[..., Awaitable[ua.CallMethodResult]]:
    """A method of a companion specification's signature: a refusal is its status code alone."""
    return checked_method(types, action, lambda refusal: [])


def text_method(types: Sequence[ua.VariantType], n_outputs: int, action: Callable[..., Awaitable[list[ua.Variant]]]
                ) -> Callable[..., Awaitable[ua.CallMethodResult]]:
    """A method of ours whose ``n_outputs`` outputs (strings) end with the ``Message`` text: a refusal is its status
    code with its text as the ``Message`` (the other outputs empty)."""
    blanks = [ua.Variant("", ua.VariantType.String)] * (n_outputs - 1)
    return checked_method(types, action, lambda refusal: [*blanks, ua.Variant(refusal.text, ua.VariantType.String)])


async def refusals_as_calls(action: Callable[..., Awaitable], *values):
    """``await action(*values)``; the facade's refusals become :class:`CallRefused`."""
    try:
        return await action(*values)
    except ApiProblem as e:
        raise CallRefused(STATUS_OF_HTTP.get(e.status, ua.StatusCodes.BadInternalError), e.detail or e.title) from e
    except JobRequestError as e:
        raise CallRefused(STATUS_OF_HTTP.get(e.status, ua.StatusCodes.BadInternalError), str(e)) from e
    except ValidationError as e:
        raise CallRefused(ua.StatusCodes.BadInvalidArgument, "; ".join(err["msg"] for err in e.errors())) from e
