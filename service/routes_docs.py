"""The API's description, served by the service itself: Swagger UI at `/docs` and ReDoc at
`/redoc` over `/openapi.json`, and the WebSocket protocol as an AsyncAPI document at
`/asyncapi.yaml` (service/asyncapi.yaml, the machine-readable form of docs/protocol.md).

The pages load their scripts from this server (`/docs/assets/`), never from a CDN, so they work
on a machine without internet. The assets come from the `fastapi-offline` wheel, which
republishes the swagger-ui-dist 5 and ReDoc 2 bundles that FastAPI would otherwise fetch from
jsDelivr (README.md, "API description", says why that package).
"""

from __future__ import annotations

import json
from importlib.resources import files
from pathlib import Path
from typing import Any

from fastapi import APIRouter, FastAPI, HTTPException, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.openapi.utils import get_openapi
from fastapi.responses import FileResponse, HTMLResponse, Response

from .api import ErrorBody

ASSETS = Path(str(files("fastapi_offline") / "static"))
ASSET_TYPES = {
    "swagger-ui-bundle.js": "text/javascript",
    "swagger-ui.css": "text/css",
    "redoc.standalone.js": "text/javascript",
    "favicon.png": "image/png",
}
ASYNCAPI_FILE = Path(__file__).resolve().parent / "asyncapi.yaml"
DESCRIPTION = """Online motion style transfer: a client streams a character's frames over a WebSocket
(`/v1/stream`) and gets each one back in the chosen style; REST lists the models and styles,
uploads new styles from a clip and follows their fine-tuning jobs.

- The streaming protocol, machine-readable: [AsyncAPI document](asyncapi.yaml) (AsyncAPI 3.1);
  with examples: docs/protocol.md in the repository.
- This page: [Swagger UI](docs) · [ReDoc](redoc) · [OpenAPI document](openapi.json).
- Every refusal is `{"code", "message"}` with its status; each route lists the statuses it answers.
"""

router = APIRouter(include_in_schema=False)


def _prefix(request: Request) -> str:
    """The path the app is mounted under (behind a proxy's prefix), so the pages' links resolve."""
    return str(request.scope.get("root_path", "")).rstrip("/")


@router.get("/docs")
async def swagger_ui(request: Request) -> HTMLResponse:
    root = _prefix(request)
    return get_swagger_ui_html(
        openapi_url=f"{root}/openapi.json",
        title="stylestream API",
        swagger_js_url=f"{root}/docs/assets/swagger-ui-bundle.js",
        swagger_css_url=f"{root}/docs/assets/swagger-ui.css",
        swagger_favicon_url=f"{root}/docs/assets/favicon.png",
        # no validator badge: it would send the document to validator.swagger.io
        swagger_ui_parameters={"validatorUrl": None, "defaultModelsExpandDepth": 0},
    )


@router.get("/redoc")
async def redoc(request: Request) -> HTMLResponse:
    root = _prefix(request)
    return get_redoc_html(
        openapi_url=f"{root}/openapi.json",
        title="stylestream API",
        redoc_js_url=f"{root}/docs/assets/redoc.standalone.js",
        redoc_favicon_url=f"{root}/docs/assets/favicon.png",
        with_google_fonts=False,
    )


@router.get("/docs/assets/{name}")
async def asset(name: str) -> FileResponse:
    """The pages' scripts, stylesheet and icon: these four files and nothing else."""
    if name not in ASSET_TYPES:
        raise HTTPException(404, "not found")
    return FileResponse(ASSETS / name, media_type=ASSET_TYPES[name], headers={"Cache-Control": "max-age=86400"})


@router.get("/asyncapi.yaml")
async def asyncapi() -> Response:
    return Response(ASYNCAPI_FILE.read_bytes(), media_type="application/yaml")


def _lift_defs(node: Any, schemas: dict[str, Any]) -> Any:
    """`node` with the `$defs` of schemas pasted in by hand (the upload body's `openapi_extra`)
    moved to the document's components and their `#/$defs/` references pointed there: in an
    OpenAPI document those references resolve from its root, where there is no `$defs` (ReDoc
    refused to render)."""
    if isinstance(node, list):
        return [_lift_defs(item, schemas) for item in node]
    if not isinstance(node, dict):
        return node
    for name, schema in node.pop("$defs", {}).items():
        schemas.setdefault(name, _lift_defs(schema, schemas))
    out = {key: _lift_defs(value, schemas) for key, value in node.items()}
    if isinstance(out.get("$ref"), str) and out["$ref"].startswith("#/$defs/"):
        out["$ref"] = "#/components/schemas/" + out["$ref"].removeprefix("#/$defs/")
    return out


def openapi_document(app: FastAPI) -> dict[str, Any]:
    """FastAPI's OpenAPI document, with its request-validation 422s described as they are
    answered: an `ErrorBody` with code `bad_request` (`api.invalid_request`), not FastAPI's
    `{"detail": [...]}`; and hand-written schemas' `$defs` lifted (`_lift_defs`). Built once,
    like FastAPI's own."""
    if app.openapi_schema is None:
        doc = get_openapi(
            title=app.title, version=app.version, description=app.description, routes=app.routes, tags=app.openapi_tags
        )
        schemas = doc.setdefault("components", {}).setdefault("schemas", {})
        schemas.setdefault("ErrorBody", ErrorBody.model_json_schema())
        doc["paths"] = _lift_defs(doc.get("paths", {}), schemas)
        for ops in doc.get("paths", {}).values():
            for op in ops.values():
                for reply in op.get("responses", {}).values():
                    schema = reply.get("content", {}).get("application/json", {}).get("schema", {})
                    if schema.get("$ref") == "#/components/schemas/HTTPValidationError":
                        schema["$ref"] = "#/components/schemas/ErrorBody"
        if "HTTPValidationError" not in json.dumps(doc["paths"]):
            schemas.pop("HTTPValidationError", None)
            schemas.pop("ValidationError", None)
        app.openapi_schema = doc
    return app.openapi_schema


def install_docs(app: FastAPI) -> None:
    """Serve the description (the app is made with `docs_url=None, redoc_url=None`, so FastAPI's
    CDN pages are not)."""
    app.description = DESCRIPTION
    app.openapi = lambda: openapi_document(app)  # type: ignore[method-assign]
    app.include_router(router)
