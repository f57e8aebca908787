"""`GET /v1/models`: the models this server streams, their current styles, joints and pipelines."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from .api import ModelInfo, error_responses
from .deps import get_runtime, require_token
from .limits import Principal
from .runtime import Runtime

router = APIRouter()


@router.get(
    "/v1/models",
    response_model=list[ModelInfo],
    dependencies=[Depends(require_token)],
    summary="The models, their styles and joints",
    tags=["models"],
    responses=error_responses(401, 429, 503),
)
async def list_models(rt: Runtime = Depends(get_runtime), who: Principal = Depends(require_token)) -> list[ModelInfo]:
    await rt.styles.refresh()  # a styles folder shared with other replicas: what it holds now
    return [
        ModelInfo(
            name=n,
            styles=[s for s in m.styles() if s not in rt.styles.hidden_from(who, n)],  # other tenants' uploads
            joints=list(m.skeleton.names),
            controllable=m.controllable,
            pipelines=rt.offered(n),
        )
        for n, m in rt.models.items()
    ]
