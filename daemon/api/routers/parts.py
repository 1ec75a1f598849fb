"""``/v1/parts``: a part number's characteristics over its serials (docs/quality.md, "Serials and trends")."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Query
from tandemscan.daemon.api.errors import ApiProblem
from tandemscan.daemon.api.facade import Facade
from tandemscan.daemon.api.models import PROBLEM_RESPONSES, CharacteristicTrend, trend_body

router = APIRouter(tags=["parts"])
Name = Annotated[str, Path(min_length=1, max_length=200)]


@router.get("/v1/parts/{part}/characteristics", response_model=list[str], responses=PROBLEM_RESPONSES)
async def list_characteristics(part: Name, facade: Facade) -> list[str]:
    """The ids of the characteristics measured on ``part`` (its part number), in the template's order."""
    return await facade.read(facade.daemon.part_results.characteristics, part)


@router.get("/v1/parts/{part}/characteristics/{characteristic}/trend", response_model=CharacteristicTrend,
            responses=PROBLEM_RESPONSES)
async def get_trend(part: Name, characteristic: Name, facade: Facade,
                    last: Annotated[int, Query(ge=1, le=1000)] = 50) -> CharacteristicTrend:
    """The characteristic's results over the last ``last`` serials of ``part`` with mean, standard deviation,
    control limits and Cp/Cpk; 404 when none was measured."""
    trend = await facade.read(facade.daemon.part_results.trend, part, characteristic, last)
    if trend is None:
        raise ApiProblem(404, "No such characteristic", f"no results of {characteristic!r} for part {part!r}")
    return trend_body(trend)
