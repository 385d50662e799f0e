"""The options of :func:`pipeline.process.process_take` and the error it raises."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

__all__ = ["MAX_RIG_SAMPLES", "ProcessError", "ProcessParams", "ProcessResult", "RigParams", "TrackParams", "check_params"]


class ProcessError(ValueError):
    """A take that cannot be processed; the message says why and what to do.

    Parameters
    ----------
    message : str
        In the words of ``stage process``: its options (``--resolution``), other ``stage`` commands.
    job_message : str, optional
        The same in the words of a job of the REST API, where ``message`` names a command line option or
        command: the job's ``parameters`` (``parameters.resolution``), the API's endpoints. The API shows this
        one (:attr:`job_message`; ``message`` when not given).
    """

    def __init__(self, message: str, *, job_message: str | None = None) -> None:
        super().__init__(message)
        self.job_message = message if job_message is None else job_message


class TrackParams(BaseModel):
    """Options of the ``track`` step, as ``stage track RESULTS_DIR`` takes them (docs/tracking.md).

    Parameters
    ----------
    carve : int
        Rounds of surfaces carved across time with the tracked motion, each tracked again
        (``--carve``; 0: the surfaces of ``stage process``).
    carve_margin : float or None
        Pixels every silhouette grows by in the carving (``--carve-margin``; default per camera
        from its calibration, :func:`pipeline.carve.carve_results`); needs ``carve``.
    shape_memory : bool
        Keep the previous frame's shape in the rigid prior (``--shape-memory``).
    colour : bool
        Feature tracks from every camera's colour images (``--colour``).
    labels : bool
        Cut the template's rigid patches at the limbs of the take's spine (``--labels``,
        :func:`pipeline.template_labels.template_labels`): the body one patch, every limb on its own grid. A job
        whose ``rig.parts`` is "limbs" tracks with them too (:attr:`ProcessParams.track_labels`).
    armature_rounds : int or "auto"
        After the tracking, at most this many rounds of an armature built from the tracked motion and the
        take tracked again with it as the articulated prior, the best round kept (``--armature-rounds``,
        :func:`pipeline.track_armature.track_with_armature`); ``"auto"``: at most
        :data:`pipeline.track_armature.AUTO_RIG_ROUNDS`; 1 (default): one round; 0: none, the tracking alone.
    spine_armature : bool
        The first armature round's armature is the take's spine (``--spine-armature``); needs
        ``armature_rounds`` other than 0 (the default, one round, is).
    armature_parts : {"motion", "limbs"}
        Where every round's armature gets its parts (``--armature-parts``): ``"motion"`` the motion
        segmentation, ``"limbs"`` the labels' body and limbs; ``"limbs"`` needs ``armature_rounds`` (not 0) and the labels
        (``labels``, or ``rig.parts`` "limbs").

    The rules between these options are ``stage track``'s, checked by :class:`ProcessParams` (which sees ``rig.parts``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    carve: Annotated[int, Field(ge=0, le=5)] = 0
    carve_margin: Annotated[float, Field(ge=0, le=10)] | None = None
    shape_memory: bool = False
    colour: bool = False
    labels: bool = False
    armature_rounds: Annotated[int, Field(ge=0, le=4)] | Literal["auto"] = 1
    spine_armature: bool = False
    armature_parts: Literal["motion", "limbs"] = "motion"


#: the most sampled vertices a job's rig segmentation takes (``RigParams.samples``)
MAX_RIG_SAMPLES = 5000


class RigParams(BaseModel):
    """Options of the ``rig`` step, as ``stage armature RESULTS_DIR`` takes them (docs/armature-format.md).

    Parameters
    ----------
    parts : {"motion", "limbs"}
        Where the armature's rigid parts come from (``--parts``): ``"motion"`` the motion segmentation;
        ``"limbs"`` for a template tracked with its limb/body labels (``TrackParams.labels``): the labels'
        body one part, every limb cut along its spine axis (:func:`pipeline.armature_files.limb_parts`).
    lambda_thr : float
        Eigenvalue threshold of the motion segmentation (``--lambda-thr``), within (0, 2): 0.7 (default) for
        pronounced motion of reasonably sized parts, 0.98 for small parts with small motion.
    samples : int
        Sampled vertices of the segmentation (``--samples``), 2 or more; at most :data:`MAX_RIG_SAMPLES` in a job
        (the segmentation's cost grows with their square).
    reference : int or None
        Position (0-based) of the rest frame among the tracked frames (``--reference``; default: of 8 evenly
        spaced frames, the one whose curve skeleton shows the most tips, :func:`pipeline.armature.choose_reference`);
        past the last surface it is refused before the take is tracked.

    The bounds are :func:`pipeline.armature.check_armature_options`', as ``stage armature`` checks them.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    parts: Literal["motion", "limbs"] = "motion"
    lambda_thr: float = 0.7
    samples: Annotated[int, Field(le=MAX_RIG_SAMPLES)] = 1000
    reference: int | None = None

    @field_validator("lambda_thr", "samples", "reference")
    @classmethod
    def _armature_bounds(cls, v, info):
        from pipeline.armature import check_armature_options

        option = {"samples": "n_samples"}.get(info.field_name, info.field_name)
        check_armature_options(**{option: v}, names={"n_samples": "samples"})  # ValueError -> ValidationError
        return v


class ProcessParams(BaseModel):
    """Options of :func:`process_take` (defaults scale with the subject and the rig).

    Attributes
    ----------
    key_mode : {"chroma", "luma", "plate"} or None
        Keying mode; default: the rig's backdrop, else chosen from the footage (a backdrop
        colour covering a large share of the views: chroma with layers; none: a plate from
        the take; :func:`stage.keying.take.choose_key_mode`). The choice and why are in
        ``process.json`` (``key``).
    key_layers : tuple of {"volume", "graphcut"} or None
        Keying layers (docs/keying.md): ``volume``, pixels whose rays miss the volume
        searched for the subject are background; ``graphcut``, the ``refine`` step cuts
        every camera's silhouettes with colour models seeded by a first hull. Default: the
        rig's, else the footage's choice.
    rekey : bool
        Key again even when the take already holds masks.
    resolution : int or None
        Voxels along the longest side of the subject's bounding box (the box is
        found by a coarse carve of the whole capture volume). Default: from the rig,
        a voxel of :data:`PIXELS_PER_VOXEL` times the median pixel footprint at the
        subject over the cameras that see it (so a limb 4 pixels wide in most views is
        2 voxels across), within :data:`MAX_VOXELS` and the memory the carver may use.
    volume : (6,) floats or None
        ``[xmin, ymin, zmin, xmax, ymax, zmax]`` to search for the subject; default the
        rig's capture volume, else derived from the cameras.
    tolerance : int
        Cameras allowed to disagree before a voxel is carved.
    silhouette_margin : int
        Pixels every silhouette grows by before carving (a conservative hull): with
        calibration and masks each a fraction of a pixel off, the intersection of many
        exact silhouettes shaves thin parts that every camera only just sees.
    support_plane : (4,) floats or None
        ``(a, b, c, d)`` of the plane the subject stands on (kept where
        ``a x + b y + c z + d >= 0``, world units). Cameras that all look down on the
        subject cannot carve the cone under its base; the plane removes it. Our own
        rigs need none (their capture volume starts at the floor); give it for imported
        footage, e.g. a turntable or pedestal at a known height.
    smooth_iterations : int
        Taubin smoothing iterations of the surface.
    face_budget : int or None
        Decimate surfaces to at most this many faces before skeletons (their cost grows
        with the faces; the tips and limbs do not need more). ``None``: never.
    chunk : int
        Frames per task sent to the executor.
    depth : {"auto", "off"}
        ``auto``: when every camera of the take delivers depth (RGB-D), fuse the depth
        frames into a truncated signed distance volume intersected with the visual hull
        and take its zero level set; ``off``: the visual hull alone.
    photo_refine : bool
        Move every hull surface's vertices along their normals to where the cameras'
        colours agree (:func:`pipeline.photo_refine.refine_surface`): the hull's excess in
        concavities that two cameras see is carved. Surfaces from fused depth are not refined.
    spine : dict
        Options of :class:`pipeline.frame_skeleton.SpineParams`.
    track : TrackParams
        Options of the ``track`` step. They change only the tracking: a run with other ones
        tracks again (``tracked/track.json`` says what changed) and keeps every other result.
    rig : RigParams
        Options of the ``rig`` step. They change the rig alone (the step builds it again every run).
    skip_damaged : bool
        A take with damaged frames (a chunk failing its checksum, :func:`stage.store.verify.verify_take`)
        is processed without the frame sets that hold them: no damaged frame is read, those sets
        get no surface (``frames/`` records them as ``damaged``) and ``process.json``, the report and
        the log list them. Off: such a take stops before any work, naming the damage. Damage outside
        the frames (metadata, the set table) always stops.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    key_mode: Literal["chroma", "luma", "plate"] | None = None
    key_layers: tuple[Literal["volume", "graphcut"], ...] | None = None
    rekey: bool = False
    resolution: Annotated[int, Field(ge=16, le=512)] | None = None
    volume: tuple[float, float, float, float, float, float] | None = None
    tolerance: Annotated[int, Field(ge=0)] = 0
    silhouette_margin: Annotated[int, Field(ge=0, le=10)] = 1
    support_plane: tuple[float, float, float, float] | None = None
    smooth_iterations: Annotated[int, Field(ge=0, le=200)] = 10
    face_budget: Annotated[int, Field(ge=100)] | None = 16000
    chunk: Annotated[int, Field(ge=1)] = 4
    depth: Literal["auto", "off"] = "auto"
    photo_refine: bool = False
    spine: dict = Field(default_factory=dict)
    track: TrackParams = Field(default_factory=TrackParams)
    rig: RigParams = Field(default_factory=RigParams)
    skip_damaged: bool = False

    @property
    def track_labels(self) -> bool:
        """Whether the ``track`` step tracks with the template's limb/body labels: ``track.labels``, or ``rig.parts``
        "limbs" (the rig's parts from the labels need a tracking with them, as ``stage armature --parts limbs`` tracks
        an untracked take with ``--labels``)."""
        return self.track.labels or self.rig.parts == "limbs"

    @model_validator(mode="after")
    def _track_options(self) -> ProcessParams:
        """``stage track``'s rules of the carving's margin and the armature rounds (:func:`pipeline.track.check_track_options`),
        in the parameters' names (an option that would do nothing is refused, not ignored), with the labels the
        tracking has (:attr:`track_labels`)."""
        from pipeline.track import check_track_options

        t = self.track
        check_track_options(carve=t.carve, carve_margin=t.carve_margin, armature_rounds=t.armature_rounds,
                            spine_armature=t.spine_armature, armature_parts=t.armature_parts, labels=self.track_labels,
                            names={k: f"track.{k}" for k in ("carve", "carve_margin", "armature_rounds", "spine_armature",
                                                             "armature_parts", "labels")})
        return self

    @field_validator("volume")
    @classmethod
    def _check_volume(cls, v: tuple[float, float, float, float, float, float] | None):
        if v is None:
            return v
        from pipeline.volume import check_bounds

        lo_hi = check_bounds(np.reshape(np.asarray(v, float), (2, 3)), "volume")  # before any step runs
        return tuple(float(x) for x in lo_hi.reshape(-1))

    @field_validator("support_plane")
    @classmethod
    def _unit_plane(cls, v: tuple[float, float, float, float] | None) -> tuple[float, float, float, float] | None:
        if v is None:
            return v
        from pipeline.volume import check_plane

        a, b, c, d = check_plane(v).tolist()  # ValueError (a zero normal) becomes a ValidationError
        return (a, b, c, d)


@dataclass
class ProcessResult:
    out: Path
    steps: tuple[str, ...]
    frames: int
    empty_frames: list[int] = field(default_factory=list)
    spine_path: Path | None = None
    report: dict = field(default_factory=dict)


def check_params(params: ProcessParams | dict | None) -> ProcessParams:
    if params is None:
        params = ProcessParams()
    elif isinstance(params, dict):
        try:
            params = ProcessParams(**params)
        except ValidationError as exc:
            raise ValueError(f"params: {exc}") from None
    elif not isinstance(params, ProcessParams):
        raise ValueError(f"params must be ProcessParams or a dict, got {type(params).__name__}")
    try:
        from pipeline.frame_skeleton import SpineParams

        SpineParams(**params.spine)
    except ValidationError as exc:
        raise ValueError(f"params.spine: {exc}") from None
    return params
