"""JSON models of the API (request metadata and responses).

Arrays never travel as JSON except the small ones that define a job: the
geometry's vector rows and the control faces of each surface group.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

__all__ = ["GeometrySpec", "SurfaceGroupSpec", "JobCreate", "JobInfo", "SurfaceGroupInfo", "DataFile",
           "Status", "JobList", "Error"]

Kind = Literal["parallel3d_vec", "cone_vec", "parallel_vec", "fanflat_vec"]

#: limits of the JSON lists (with BUBSUB_MAX_JSON_BYTES they bound what parsing a job may allocate)
MAX_ANGLES = 100_000
MAX_CONTROL = 10_000_000
MAX_GROUPS = 10_000
MAX_FACES = 2_000_000  # control triangles of all groups together
MAX_SURFACES = 1_000_000  # surfaces of all groups together

#: one ASTRA vector row: 6 values (2D) or 12 (3D)
VectorRow = Annotated[list[float], Field(min_length=6, max_length=12)]
#: one control triangle: three vertex indices (bounded, so they always fit int64)
Triangle = Annotated[list[Annotated[int, Field(ge=0, lt=MAX_CONTROL)]], Field(min_length=3, max_length=3)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class GeometrySpec(_Strict):
    """A :class:`~bubsub.core.ScanGeometry` in ASTRA vector form."""

    kind: Kind
    vectors: list[VectorRow] = Field(..., min_length=1, max_length=MAX_ANGLES,
                                       description="one ASTRA vector row per projection: 12 values (3D) or 6 (2D)")
    det_rows: int | None = Field(None, ge=1, le=1_000_000, description="detector rows (3D kinds only)")
    det_cols: int = Field(..., ge=1, le=1_000_000, description="detector columns (det_count in 2D)")


class SurfaceGroupSpec(_Strict):
    """``count`` consecutive surfaces sharing topology, levels and attenuation.

    3D: ``faces`` are the control triangles (indices into the surface's own
    ``n_control`` vertices). 2D: ``faces`` is omitted (a closed control
    polygon of ``n_control`` points).
    """

    n_control: int = Field(..., ge=3, le=MAX_CONTROL, description="control vertices per surface")
    faces: list[Triangle] | None = Field(None, max_length=MAX_FACES,
                                          description="control triangles (m, 3), 3D only")
    levels: int = Field(2, ge=0, le=6, description="subdivision levels")
    attenuation: float = Field(..., description="attenuation inside the surfaces, 1/mm")
    count: int = Field(1, ge=1, le=MAX_SURFACES, description="number of surfaces in this group")

    @field_validator("attenuation")
    @classmethod
    def _finite(cls, v):
        if not math.isfinite(v):
            raise ValueError("attenuation must be finite")
        return v


class JobCreate(_Strict):
    """Metadata of a new job (the ``job`` part of a multipart body, or the whole JSON body)."""

    geometry: GeometrySpec
    surfaces: list[SurfaceGroupSpec] = Field(..., min_length=1, max_length=MAX_GROUPS)
    supersampling: int = Field(1, ge=1, le=64)
    compute_timeout_seconds: float | None = Field(
        None, gt=0, description="longest one forward, vjp or objective of this job may compute, seconds; at most "
                                "the server's BUBSUB_COMPUTE_TIMEOUT_SECONDS (its value when omitted)")

    @model_validator(mode="after")
    def _totals(self):
        faces = sum(len(s.faces or ()) for s in self.surfaces)
        if faces > MAX_FACES:
            raise ValueError(f"the groups have {faces} control faces together, over the limit of {MAX_FACES}")
        surfaces = sum(s.count for s in self.surfaces)
        if surfaces > MAX_SURFACES:
            raise ValueError(f"the groups have {surfaces} surfaces together, over the limit of {MAX_SURFACES}")
        return self


class SurfaceGroupInfo(BaseModel):
    n_control: int
    n_faces: int | None
    levels: int
    attenuation: float
    count: int
    n_fine: int | None = Field(None, description="fine vertices per surface, once the topology is built")


class JobInfo(BaseModel):
    """What a job holds."""

    id: str
    kind: str
    ndim: int
    n_angles: int
    projection_shape: list[int]
    vertices_shape: list[int] = Field(..., description="shape of the stacked control vertices a request sends")
    supersampling: int
    surfaces: list[SurfaceGroupInfo]
    n_surfaces: int
    has_data: bool
    has_background: bool
    memory_bytes: int
    created: float = Field(..., description="Unix time")
    idle_seconds: float
    expires_in_seconds: float
    calls: int
    compute_seconds: float
    compute_timeout_seconds: float = Field(..., description="past this a computation is stopped and answered 504")


class JobList(BaseModel):
    jobs: list[JobInfo]


class DataFile(_Strict):
    """Load an array from a file in the server's scan directory (``BUBSUB_SCAN_DIR``)."""

    file: str = Field(..., min_length=1, max_length=1024, description="path relative to the scan directory")
    key: str | None = Field(None, max_length=256, description="array name inside an .npz file")


class Error(BaseModel):
    """Body of every error response."""

    code: str = Field(..., examples=["unknown_job"], description="machine-readable error code")
    detail: str = Field(..., description="what is wrong, in words")


class Status(BaseModel):
    status: str
    detail: str | None = None
