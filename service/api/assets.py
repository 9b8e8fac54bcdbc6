"""Assets: uploading a model (PLY) or an image set, reading its metadata."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request, Response
from fastapi.concurrency import run_in_threadpool

from service.api.deps import AppBackend, Owner
from service.api.jobs import _decode_cursor as decode_cursor
from service.api.jobs import _encode_cursor as encode_cursor
from service.api.openapi import UPLOAD_BODY, problem_responses
from service.api.schemas import AssetList, AssetOut
from service.api.upload import parse_multipart
from service.jobs import core, retention
from service.problems import invalid_input

router = APIRouter()


@router.post(
    "/v1/assets",
    operation_id="uploadAsset",
    status_code=201,
    response_model=AssetOut,
    tags=["assets"],
    summary="Upload a model (PLY) or an image set (zip or several images)",
    openapi_extra=UPLOAD_BODY,
    responses=problem_responses(401, 413, 422),
)
async def upload_asset(request: Request, response: Response, owner: Owner, b: AppBackend):
    s = b.settings
    form = await parse_multipart(request, s.max_upload_bytes, max_files=s.max_images)
    try:
        files = form.files.get("file", [])
        if not files:
            raise invalid_input("multipart field 'file' is required")
        if len(files) == 1:
            asset = await run_in_threadpool(core.ingest, b, owner, files[0].file, files[0].filename)
        else:
            asset = await run_in_threadpool(
                core.ingest_images,
                b,
                owner,
                [(f.filename, f.file) for f in files],
                "images",
            )
    finally:
        form.close()
    response.headers["Location"] = f"/v1/assets/{asset.id}"
    return AssetOut.from_asset(asset)


@router.get(
    "/v1/assets",
    operation_id="listAssets",
    response_model=AssetList,
    tags=["assets"],
    summary="List your assets, newest first",
    description="Every asset of the caller's tenant (never another's), `limit` a page, the next page "
    "from `next_cursor` as in listJobs: an asset whose id was lost can be found and deleted.",
    responses=problem_responses(401, 422),
)
async def list_assets(
    owner: Owner,
    b: AppBackend,
    limit: Annotated[int, Query(ge=1, le=200)] = 50,
    cursor: str | None = None,
):
    # the cursor of listJobs: (created_at, id) of the page's last item, base64 JSON
    assets = await run_in_threadpool(b.store.list_assets, owner, limit + 1, decode_cursor(cursor) if cursor else None)
    more = len(assets) > limit
    assets = assets[:limit]
    return AssetList(
        items=[AssetOut.from_asset(a) for a in assets],
        next_cursor=encode_cursor(assets[-1]) if more and assets else None,
    )


@router.get(
    "/v1/assets/{asset_id}",
    operation_id="getAsset",
    response_model=AssetOut,
    tags=["assets"],
    summary="Asset metadata",
    responses=problem_responses(401, 404),
)
async def get_asset(asset_id: str, owner: Owner, b: AppBackend):
    return AssetOut.from_asset(core.get_asset(b, owner, asset_id))


@router.delete(
    "/v1/assets/{asset_id}",
    operation_id="deleteAsset",
    status_code=204,
    response_class=Response,
    tags=["assets"],
    summary="Delete an asset",
    description="409 asset-in-use while a queued or running job reads it. Identical uploads share one "
    "stored copy; the bytes go with the last asset that uses them.",
    responses=problem_responses(401, 404, 409),
)
async def delete_asset(asset_id: str, owner: Owner, b: AppBackend):
    await run_in_threadpool(retention.delete_asset, b, owner, asset_id)
    return Response(status_code=204)
