"""The bodies the service's API takes, as pydantic models, and the OpenAPI document built from them and the route
table (``GET /openapi.json``; docs/service.md shows every call with curl)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from hil.service._lease import MAX_TTL_S, MIN_TTL_S


class _Body(BaseModel):
    """A request body: no unknown field, no value of another type ('yes' is not a bool, '300' not a number)."""

    model_config = ConfigDict(extra="forbid", strict=True)


# a reason goes into the history and the log: text without control characters (in the schema, so a client knows)
PlainText = Annotated[str, Field(pattern=r"^[^\u0000-\u001f\u007f-\u009f]*$")]


def _integral(value: Any) -> Any:
    """JSON Schema's integer: 62.0 is 62 (a string is still no number)."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


Position = Annotated[int, BeforeValidator(_integral)]


class SubmitItem(_Body):
    """An item: the text of a YAML file the command line takes, with its file name (errors name it)."""

    kind: Literal["session", "ident", "campaign"] = "session"
    file_name: str = Field(min_length=1, max_length=100, description="the file's name, e.g. demo.yaml")
    body: str = Field(description="the file's text (a session as loaded: controller, profile and limits inline)")
    files: dict[str, str] = Field(
        default_factory=dict, max_length=64,
        description="the item's own files, by the relative name the item's file gives them (a campaign's session "
        "and profiles); nothing else is read (docs/service.md, \"A submitted item stands on its own\")")
    options: dict[str, Any] = Field(default_factory=dict, description="ident: {axis: el|az, f_start_hz, ...}")
    position: Position | None = Field(default=None, ge=0, le=1_000_000,
                                 description="where in the queue (default: at its end)")


class MoveItem(_Body):
    position: Position = Field(ge=0, le=1_000_000, description="0: first among the waiting items")


class StartQueue(_Body):
    stop_on_failure: bool = Field(default=False, description="stop the queue after an item that did not complete")


class EndItem(_Body):
    uid: str | None = Field(default=None, max_length=64,
                            description="the running item's uid (refused if another one runs)")
    reason: PlainText = Field(default="", max_length=500, description="why; it goes into the history and the log")


class TakeLease(_Body):
    ttl_s: float = Field(default=300.0, ge=MIN_TTL_S, le=MAX_TTL_S,
                         description="the lease lapses unless renewed (taken again) within this time")


class BreakLease(_Body):
    reason: PlainText = Field(min_length=1, max_length=500, description="why; it goes into the lease history")


ERROR_SCHEMA: dict[str, Any] = {"type": "object", "required": ["detail"], "additionalProperties": False,
                                "properties": {"detail": {"type": "string", "description": "one line"}}}
# every route may answer these: the Host and Origin checks, the token, the state store
COMMON_ERRORS = {"400": "bad request: the Host is not this service's, the body is not JSON",
                 "401": "no valid token (a service with tokens)",
                 "403": "another site's page (Origin), or an operator's action asked by a viewer",
                 "404": "no such item or record",
                 "429": "too many requests from this client (Retry-After says when to ask again)",
                 "503": "the state store cannot be read or written now",
                 "507": "the state store's disk is full; nothing was changed"}
BODY_ERRORS = {"409": "not now (the lease, a running item)",
               "413": "the body is larger than 2 MiB",
               "415": "the body is not Content-Type: application/json",
               "422": "bad input: one line naming the field or the file"}
# the files of an item's directory (GET /api/history/{uid}/files): by suffix, their kind and media type
FILE_KINDS = {".h5": ("log", "application/x-hdf5"), ".png": ("plot", "image/png"), ".html": ("report", "text/html"),
              ".md": ("report", "text/markdown"), ".json": ("data", "application/json"), ".csv": ("data", "text/csv"),
              ".parquet": ("data", "application/vnd.apache.parquet"), ".yaml": ("config", "application/yaml"),
              ".yml": ("config", "application/yaml"), ".txt": ("text", "text/plain"), ".log": ("text", "text/plain")}
OTHER_FILE = ("file", "application/octet-stream")
ITEM_FILE = "/api/history/{uid}/files/{path}"  # {path}: the rest of the URL, slashes and all
FILE_TYPES = {"/api/history/{uid}/log": ("application/x-hdf5",), "/api/history/{uid}/report": ("text/html",),
              ITEM_FILE: tuple(sorted({media for _kind, media in (*FILE_KINDS.values(), OTHER_FILE)}))}
QUERY = {"/api/history": ("limit", "limit is not an integer"),
         "/api/history/{uid}/series": ("max_points", "max_points is not an integer")}
SUCCESS = {"/api/queue/items": "201", "/api/bench/doctor": "202"}


def openapi_document(routes: list[tuple[Any, ...]], version: str) -> dict[str, Any]:
    """OpenAPI 3.1 for ``routes`` ((method, path, handler, operator action, body model, summary) each): every
    route with its parameters, its body's JSON schema, and every status it may answer with its schema (errors are
    all ``{"detail": "one line"}``)."""
    paths: dict[str, dict[str, Any]] = {}
    schemas: dict[str, Any] = {"Error": ERROR_SCHEMA}
    error = {"application/json": {"schema": {"$ref": "#/components/schemas/Error"}}}
    binary = {"type": "string", "format": "binary"}
    for method, path, _handler, operator, model, summary in routes:
        ok = SUCCESS.get(path, "200") if method == "POST" else "200"
        files = FILE_TYPES.get(path)
        content = ({media: {"schema": {} if media == "application/json" else binary} for media in files} if files
                   else {"application/json": {"schema": {"type": "object"}}})
        responses: dict[str, Any] = {ok: {"description": "the answer", "content": content}}
        if files:  # a file: a client may ask for a part of it (Range)
            responses["206"] = {"description": "the part of the file asked for",
                                "content": {media: {"schema": binary} for media in files}}
            responses["416"] = {"description": "a Range beyond the file"}
        responses.update({code: {"description": text, "content": error} for code, text in COMMON_ERRORS.items()})
        if method != "GET":
            responses.update({code: {"description": text, "content": error} for code, text in BODY_ERRORS.items()})
        if path in QUERY:
            responses["422"] = {"description": QUERY[path][1], "content": error}
        op: dict[str, Any] = {"summary": summary, "operationId": f"{method.lower()}_{_op_name(path)}",
                              "responses": responses}
        params = [{"name": p, "in": "path", "required": True, "schema": {"type": "string"}}
                  for p in _path_params(path)]
        if path in QUERY:
            params.append({"name": QUERY[path][0], "in": "query", "required": False, "schema": {"type": "integer"}})
        if params:
            op["parameters"] = params
        if operator is not None:
            op["description"] = f"Operators only ({operator})."
        if model is not None:
            schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
            schemas.update(schema.pop("$defs", {}))
            schemas[model.__name__] = schema
            op["requestBody"] = {"required": bool(schema.get("required")), "content": {"application/json": {
                "schema": {"$ref": f"#/components/schemas/{model.__name__}"}}}}
        paths.setdefault(path, {})[method.lower()] = op
    return {"openapi": "3.1.0",
            "info": {"title": "hil serve", "version": version,
                     "description": "The bench as a lab service (docs/service.md). Authenticate with "
                                    "Authorization: Bearer TOKEN when the service has tokens. The live feed is the "
                                    "WebSocket /ws (status and live messages). Same origin only: a request that "
                                    "changes state and carries an Origin must come from the service's own pages; "
                                    "POST bodies are application/json."},
            "paths": paths, "components": {"schemas": schemas}}


def _path_params(path: str) -> list[str]:
    return [part[1:-1] for part in path.split("/") if part.startswith("{")]


def _op_name(path: str) -> str:
    return "_".join(p.strip("{}") for p in path.split("/") if p and p != "api").replace(".", "_") or "index"
