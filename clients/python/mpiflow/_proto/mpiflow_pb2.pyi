from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Field(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FIELD_UNSPECIFIED: _ClassVar[Field]
    FIELD_IMAGE1: _ClassVar[Field]
    FIELD_IMAGE2: _ClassVar[Field]
    FIELD_FLOW: _ClassVar[Field]
    FIELD_VALID: _ClassVar[Field]
    FIELD_OCCLUSION: _ClassVar[Field]
    FIELD_MASK1: _ClassVar[Field]
    FIELD_MASK2: _ClassVar[Field]
    FIELD_DEPTH1: _ClassVar[Field]
    FIELD_DEPTH2: _ClassVar[Field]
    FIELD_HOLES: _ClassVar[Field]
    FIELD_FLOW_BACKWARD: _ClassVar[Field]
    FIELD_VALID_BACKWARD: _ClassVar[Field]
    FIELD_OCCLUSION_BACKWARD: _ClassVar[Field]
    FIELD_DISPARITY: _ClassVar[Field]

class DType(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DTYPE_UNSPECIFIED: _ClassVar[DType]
    DTYPE_U8: _ClassVar[DType]
    DTYPE_F16: _ClassVar[DType]
    DTYPE_F32: _ClassVar[DType]

class FlowDtype(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FLOW_DTYPE_UNSPECIFIED: _ClassVar[FlowDtype]
    FLOW_DTYPE_F32: _ClassVar[FlowDtype]
    FLOW_DTYPE_F16: _ClassVar[FlowDtype]

class Compression(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    COMPRESSION_UNSPECIFIED: _ClassVar[Compression]
    COMPRESSION_NONE: _ClassVar[Compression]
    COMPRESSION_LZ4: _ClassVar[Compression]

class CropMode(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    CROP_MODE_UNSPECIFIED: _ClassVar[CropMode]
    CROP_MODE_CENTER: _ClassVar[CropMode]
    CROP_MODE_RANDOM: _ClassVar[CropMode]
FIELD_UNSPECIFIED: Field
FIELD_IMAGE1: Field
FIELD_IMAGE2: Field
FIELD_FLOW: Field
FIELD_VALID: Field
FIELD_OCCLUSION: Field
FIELD_MASK1: Field
FIELD_MASK2: Field
FIELD_DEPTH1: Field
FIELD_DEPTH2: Field
FIELD_HOLES: Field
FIELD_FLOW_BACKWARD: Field
FIELD_VALID_BACKWARD: Field
FIELD_OCCLUSION_BACKWARD: Field
FIELD_DISPARITY: Field
DTYPE_UNSPECIFIED: DType
DTYPE_U8: DType
DTYPE_F16: DType
DTYPE_F32: DType
FLOW_DTYPE_UNSPECIFIED: FlowDtype
FLOW_DTYPE_F32: FlowDtype
FLOW_DTYPE_F16: FlowDtype
COMPRESSION_UNSPECIFIED: Compression
COMPRESSION_NONE: Compression
COMPRESSION_LZ4: Compression
CROP_MODE_UNSPECIFIED: CropMode
CROP_MODE_CENTER: CropMode
CROP_MODE_RANDOM: CropMode

class OutputCrop(_message.Message):
    __slots__ = ("width", "height", "mode")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    mode: CropMode
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., mode: _Optional[_Union[CropMode, str]] = ...) -> None: ...

class SampleSpec(_message.Message):
    __slots__ = ("dataset", "fingerprint", "seed", "fields", "flow_dtype", "compression", "crop", "motion_preset", "motion_ranges_json", "max_objects", "motions_per_image", "augment", "frames", "resample")
    DATASET_FIELD_NUMBER: _ClassVar[int]
    FINGERPRINT_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    FIELDS_FIELD_NUMBER: _ClassVar[int]
    FLOW_DTYPE_FIELD_NUMBER: _ClassVar[int]
    COMPRESSION_FIELD_NUMBER: _ClassVar[int]
    CROP_FIELD_NUMBER: _ClassVar[int]
    MOTION_PRESET_FIELD_NUMBER: _ClassVar[int]
    MOTION_RANGES_JSON_FIELD_NUMBER: _ClassVar[int]
    MAX_OBJECTS_FIELD_NUMBER: _ClassVar[int]
    MOTIONS_PER_IMAGE_FIELD_NUMBER: _ClassVar[int]
    AUGMENT_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    RESAMPLE_FIELD_NUMBER: _ClassVar[int]
    dataset: str
    fingerprint: int
    seed: int
    fields: _containers.RepeatedScalarFieldContainer[Field]
    flow_dtype: FlowDtype
    compression: Compression
    crop: OutputCrop
    motion_preset: str
    motion_ranges_json: str
    max_objects: int
    motions_per_image: int
    augment: str
    frames: int
    resample: str
    def __init__(self, dataset: _Optional[str] = ..., fingerprint: _Optional[int] = ..., seed: _Optional[int] = ..., fields: _Optional[_Iterable[_Union[Field, str]]] = ..., flow_dtype: _Optional[_Union[FlowDtype, str]] = ..., compression: _Optional[_Union[Compression, str]] = ..., crop: _Optional[_Union[OutputCrop, _Mapping]] = ..., motion_preset: _Optional[str] = ..., motion_ranges_json: _Optional[str] = ..., max_objects: _Optional[int] = ..., motions_per_image: _Optional[int] = ..., augment: _Optional[str] = ..., frames: _Optional[int] = ..., resample: _Optional[str] = ...) -> None: ...

class StreamRequest(_message.Message):
    __slots__ = ("spec", "rank", "world_size", "start_index", "count", "batch_size", "prefetch")
    SPEC_FIELD_NUMBER: _ClassVar[int]
    RANK_FIELD_NUMBER: _ClassVar[int]
    WORLD_SIZE_FIELD_NUMBER: _ClassVar[int]
    START_INDEX_FIELD_NUMBER: _ClassVar[int]
    COUNT_FIELD_NUMBER: _ClassVar[int]
    BATCH_SIZE_FIELD_NUMBER: _ClassVar[int]
    PREFETCH_FIELD_NUMBER: _ClassVar[int]
    spec: SampleSpec
    rank: int
    world_size: int
    start_index: int
    count: int
    batch_size: int
    prefetch: int
    def __init__(self, spec: _Optional[_Union[SampleSpec, _Mapping]] = ..., rank: _Optional[int] = ..., world_size: _Optional[int] = ..., start_index: _Optional[int] = ..., count: _Optional[int] = ..., batch_size: _Optional[int] = ..., prefetch: _Optional[int] = ...) -> None: ...

class SampleRequest(_message.Message):
    __slots__ = ("spec", "index")
    SPEC_FIELD_NUMBER: _ClassVar[int]
    INDEX_FIELD_NUMBER: _ClassVar[int]
    spec: SampleSpec
    index: int
    def __init__(self, spec: _Optional[_Union[SampleSpec, _Mapping]] = ..., index: _Optional[int] = ...) -> None: ...

class SamplesRequest(_message.Message):
    __slots__ = ("spec", "indices")
    SPEC_FIELD_NUMBER: _ClassVar[int]
    INDICES_FIELD_NUMBER: _ClassVar[int]
    spec: SampleSpec
    indices: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, spec: _Optional[_Union[SampleSpec, _Mapping]] = ..., indices: _Optional[_Iterable[int]] = ...) -> None: ...

class Tensor(_message.Message):
    __slots__ = ("name", "shape", "dtype", "compression", "raw_size", "data")
    NAME_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    COMPRESSION_FIELD_NUMBER: _ClassVar[int]
    RAW_SIZE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    name: str
    shape: _containers.RepeatedScalarFieldContainer[int]
    dtype: DType
    compression: Compression
    raw_size: int
    data: bytes
    def __init__(self, name: _Optional[str] = ..., shape: _Optional[_Iterable[int]] = ..., dtype: _Optional[_Union[DType, str]] = ..., compression: _Optional[_Union[Compression, str]] = ..., raw_size: _Optional[int] = ..., data: _Optional[bytes] = ...) -> None: ...

class Motion(_message.Message):
    __slots__ = ("law", "translation", "axis_angle", "rotation", "rotation_kind", "angles")
    LAW_FIELD_NUMBER: _ClassVar[int]
    TRANSLATION_FIELD_NUMBER: _ClassVar[int]
    AXIS_ANGLE_FIELD_NUMBER: _ClassVar[int]
    ROTATION_FIELD_NUMBER: _ClassVar[int]
    ROTATION_KIND_FIELD_NUMBER: _ClassVar[int]
    ANGLES_FIELD_NUMBER: _ClassVar[int]
    law: str
    translation: _containers.RepeatedScalarFieldContainer[float]
    axis_angle: _containers.RepeatedScalarFieldContainer[float]
    rotation: _containers.RepeatedScalarFieldContainer[float]
    rotation_kind: str
    angles: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, law: _Optional[str] = ..., translation: _Optional[_Iterable[float]] = ..., axis_angle: _Optional[_Iterable[float]] = ..., rotation: _Optional[_Iterable[float]] = ..., rotation_kind: _Optional[str] = ..., angles: _Optional[_Iterable[float]] = ...) -> None: ...

class ObjectMotion(_message.Message):
    __slots__ = ("label", "instance", "score", "area", "motion")
    LABEL_FIELD_NUMBER: _ClassVar[int]
    INSTANCE_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    AREA_FIELD_NUMBER: _ClassVar[int]
    MOTION_FIELD_NUMBER: _ClassVar[int]
    label: int
    instance: int
    score: float
    area: float
    motion: Motion
    def __init__(self, label: _Optional[int] = ..., instance: _Optional[int] = ..., score: _Optional[float] = ..., area: _Optional[float] = ..., motion: _Optional[_Union[Motion, _Mapping]] = ...) -> None: ...

class Intrinsics(_message.Message):
    __slots__ = ("fx", "fy", "cx", "cy")
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    fx: float
    fy: float
    cx: float
    cy: float
    def __init__(self, fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ...) -> None: ...

class Timings(_message.Message):
    __slots__ = ("scene_ms", "render_ms", "objects_ms", "merge_ms", "inpaint_ms", "total_ms", "encode_ms")
    SCENE_MS_FIELD_NUMBER: _ClassVar[int]
    RENDER_MS_FIELD_NUMBER: _ClassVar[int]
    OBJECTS_MS_FIELD_NUMBER: _ClassVar[int]
    MERGE_MS_FIELD_NUMBER: _ClassVar[int]
    INPAINT_MS_FIELD_NUMBER: _ClassVar[int]
    TOTAL_MS_FIELD_NUMBER: _ClassVar[int]
    ENCODE_MS_FIELD_NUMBER: _ClassVar[int]
    scene_ms: float
    render_ms: float
    objects_ms: float
    merge_ms: float
    inpaint_ms: float
    total_ms: float
    encode_ms: float
    def __init__(self, scene_ms: _Optional[float] = ..., render_ms: _Optional[float] = ..., objects_ms: _Optional[float] = ..., merge_ms: _Optional[float] = ..., inpaint_ms: _Optional[float] = ..., total_ms: _Optional[float] = ..., encode_ms: _Optional[float] = ...) -> None: ...

class Sample(_message.Message):
    __slots__ = ("index", "dataset", "fingerprint", "seed", "source_id", "width", "height", "tensors", "camera", "objects", "intrinsics", "timings", "skipped_sources", "crop_x", "crop_y", "inpainted_pixels", "provenance", "augment", "frames")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    DATASET_FIELD_NUMBER: _ClassVar[int]
    FINGERPRINT_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    SOURCE_ID_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    TENSORS_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    OBJECTS_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    TIMINGS_FIELD_NUMBER: _ClassVar[int]
    SKIPPED_SOURCES_FIELD_NUMBER: _ClassVar[int]
    CROP_X_FIELD_NUMBER: _ClassVar[int]
    CROP_Y_FIELD_NUMBER: _ClassVar[int]
    INPAINTED_PIXELS_FIELD_NUMBER: _ClassVar[int]
    PROVENANCE_FIELD_NUMBER: _ClassVar[int]
    AUGMENT_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    index: int
    dataset: str
    fingerprint: int
    seed: int
    source_id: str
    width: int
    height: int
    tensors: _containers.RepeatedCompositeFieldContainer[Tensor]
    camera: Motion
    objects: _containers.RepeatedCompositeFieldContainer[ObjectMotion]
    intrinsics: Intrinsics
    timings: Timings
    skipped_sources: int
    crop_x: int
    crop_y: int
    inpainted_pixels: int
    provenance: _containers.RepeatedScalarFieldContainer[str]
    augment: str
    frames: int
    def __init__(self, index: _Optional[int] = ..., dataset: _Optional[str] = ..., fingerprint: _Optional[int] = ..., seed: _Optional[int] = ..., source_id: _Optional[str] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., tensors: _Optional[_Iterable[_Union[Tensor, _Mapping]]] = ..., camera: _Optional[_Union[Motion, _Mapping]] = ..., objects: _Optional[_Iterable[_Union[ObjectMotion, _Mapping]]] = ..., intrinsics: _Optional[_Union[Intrinsics, _Mapping]] = ..., timings: _Optional[_Union[Timings, _Mapping]] = ..., skipped_sources: _Optional[int] = ..., crop_x: _Optional[int] = ..., crop_y: _Optional[int] = ..., inpainted_pixels: _Optional[int] = ..., provenance: _Optional[_Iterable[str]] = ..., augment: _Optional[str] = ..., frames: _Optional[int] = ...) -> None: ...

class SampleBatch(_message.Message):
    __slots__ = ("samples", "next_index", "resume_start_index")
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    NEXT_INDEX_FIELD_NUMBER: _ClassVar[int]
    RESUME_START_INDEX_FIELD_NUMBER: _ClassVar[int]
    samples: _containers.RepeatedCompositeFieldContainer[Sample]
    next_index: int
    resume_start_index: int
    def __init__(self, samples: _Optional[_Iterable[_Union[Sample, _Mapping]]] = ..., next_index: _Optional[int] = ..., resume_start_index: _Optional[int] = ...) -> None: ...

class SourceChunk(_message.Message):
    __slots__ = ("dataset", "name", "kind", "data")
    DATASET_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    dataset: str
    name: str
    kind: str
    data: bytes
    def __init__(self, dataset: _Optional[str] = ..., name: _Optional[str] = ..., kind: _Optional[str] = ..., data: _Optional[bytes] = ...) -> None: ...

class UploadSummary(_message.Message):
    __slots__ = ("dataset", "accepted", "rejected", "fingerprint", "sources")
    DATASET_FIELD_NUMBER: _ClassVar[int]
    ACCEPTED_FIELD_NUMBER: _ClassVar[int]
    REJECTED_FIELD_NUMBER: _ClassVar[int]
    FINGERPRINT_FIELD_NUMBER: _ClassVar[int]
    SOURCES_FIELD_NUMBER: _ClassVar[int]
    dataset: str
    accepted: int
    rejected: _containers.RepeatedScalarFieldContainer[str]
    fingerprint: int
    sources: int
    def __init__(self, dataset: _Optional[str] = ..., accepted: _Optional[int] = ..., rejected: _Optional[_Iterable[str]] = ..., fingerprint: _Optional[int] = ..., sources: _Optional[int] = ...) -> None: ...

class InfoRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class DatasetInfo(_message.Message):
    __slots__ = ("name", "fingerprint", "sources", "description", "is_default", "skipped", "needs_models", "baked_with")
    class SkippedEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    NAME_FIELD_NUMBER: _ClassVar[int]
    FINGERPRINT_FIELD_NUMBER: _ClassVar[int]
    SOURCES_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTION_FIELD_NUMBER: _ClassVar[int]
    IS_DEFAULT_FIELD_NUMBER: _ClassVar[int]
    SKIPPED_FIELD_NUMBER: _ClassVar[int]
    NEEDS_MODELS_FIELD_NUMBER: _ClassVar[int]
    BAKED_WITH_FIELD_NUMBER: _ClassVar[int]
    name: str
    fingerprint: int
    sources: int
    description: str
    is_default: bool
    skipped: _containers.ScalarMap[str, int]
    needs_models: bool
    baked_with: str
    def __init__(self, name: _Optional[str] = ..., fingerprint: _Optional[int] = ..., sources: _Optional[int] = ..., description: _Optional[str] = ..., is_default: _Optional[bool] = ..., skipped: _Optional[_Mapping[str, int]] = ..., needs_models: _Optional[bool] = ..., baked_with: _Optional[str] = ...) -> None: ...

class ModelInfo(_message.Message):
    __slots__ = ("role", "name")
    ROLE_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    role: str
    name: str
    def __init__(self, role: _Optional[str] = ..., name: _Optional[str] = ...) -> None: ...

class Limits(_message.Message):
    __slots__ = ("max_message_bytes", "max_streams", "max_batch_size", "max_prefetch", "max_image_side", "max_image_pixels", "max_upload_bytes", "max_indices", "max_buffered_bytes", "max_request_bytes", "max_random_access_calls", "max_connections", "max_connections_per_peer", "max_calls_per_connection", "idle_connection_timeout_s", "stall_timeout_s")
    MAX_MESSAGE_BYTES_FIELD_NUMBER: _ClassVar[int]
    MAX_STREAMS_FIELD_NUMBER: _ClassVar[int]
    MAX_BATCH_SIZE_FIELD_NUMBER: _ClassVar[int]
    MAX_PREFETCH_FIELD_NUMBER: _ClassVar[int]
    MAX_IMAGE_SIDE_FIELD_NUMBER: _ClassVar[int]
    MAX_IMAGE_PIXELS_FIELD_NUMBER: _ClassVar[int]
    MAX_UPLOAD_BYTES_FIELD_NUMBER: _ClassVar[int]
    MAX_INDICES_FIELD_NUMBER: _ClassVar[int]
    MAX_BUFFERED_BYTES_FIELD_NUMBER: _ClassVar[int]
    MAX_REQUEST_BYTES_FIELD_NUMBER: _ClassVar[int]
    MAX_RANDOM_ACCESS_CALLS_FIELD_NUMBER: _ClassVar[int]
    MAX_CONNECTIONS_FIELD_NUMBER: _ClassVar[int]
    MAX_CONNECTIONS_PER_PEER_FIELD_NUMBER: _ClassVar[int]
    MAX_CALLS_PER_CONNECTION_FIELD_NUMBER: _ClassVar[int]
    IDLE_CONNECTION_TIMEOUT_S_FIELD_NUMBER: _ClassVar[int]
    STALL_TIMEOUT_S_FIELD_NUMBER: _ClassVar[int]
    max_message_bytes: int
    max_streams: int
    max_batch_size: int
    max_prefetch: int
    max_image_side: int
    max_image_pixels: int
    max_upload_bytes: int
    max_indices: int
    max_buffered_bytes: int
    max_request_bytes: int
    max_random_access_calls: int
    max_connections: int
    max_connections_per_peer: int
    max_calls_per_connection: int
    idle_connection_timeout_s: float
    stall_timeout_s: float
    def __init__(self, max_message_bytes: _Optional[int] = ..., max_streams: _Optional[int] = ..., max_batch_size: _Optional[int] = ..., max_prefetch: _Optional[int] = ..., max_image_side: _Optional[int] = ..., max_image_pixels: _Optional[int] = ..., max_upload_bytes: _Optional[int] = ..., max_indices: _Optional[int] = ..., max_buffered_bytes: _Optional[int] = ..., max_request_bytes: _Optional[int] = ..., max_random_access_calls: _Optional[int] = ..., max_connections: _Optional[int] = ..., max_connections_per_peer: _Optional[int] = ..., max_calls_per_connection: _Optional[int] = ..., idle_connection_timeout_s: _Optional[float] = ..., stall_timeout_s: _Optional[float] = ...) -> None: ...

class InfoResponse(_message.Message):
    __slots__ = ("version", "datasets", "models", "limits", "workers", "serving", "simd")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    DATASETS_FIELD_NUMBER: _ClassVar[int]
    MODELS_FIELD_NUMBER: _ClassVar[int]
    LIMITS_FIELD_NUMBER: _ClassVar[int]
    WORKERS_FIELD_NUMBER: _ClassVar[int]
    SERVING_FIELD_NUMBER: _ClassVar[int]
    SIMD_FIELD_NUMBER: _ClassVar[int]
    version: str
    datasets: _containers.RepeatedCompositeFieldContainer[DatasetInfo]
    models: _containers.RepeatedCompositeFieldContainer[ModelInfo]
    limits: Limits
    workers: int
    serving: bool
    simd: str
    def __init__(self, version: _Optional[str] = ..., datasets: _Optional[_Iterable[_Union[DatasetInfo, _Mapping]]] = ..., models: _Optional[_Iterable[_Union[ModelInfo, _Mapping]]] = ..., limits: _Optional[_Union[Limits, _Mapping]] = ..., workers: _Optional[int] = ..., serving: _Optional[bool] = ..., simd: _Optional[str] = ...) -> None: ...
