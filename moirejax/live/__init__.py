"""Live sensing: cameras by name, frame sources, rectification, the GateER contact gate, vision mode, output
sinks (JSON lines, UDP, MCAP for ROS 2), the live loop, the in-process sensor handle, and
several sensors on one gripper.

This is I/O and control code in numpy/OpenCV around the differentiable core: the wrench
inversion plugs in as `process_tactile` of [`run_pipeline`][].
"""

from ._camera import (
    AbstractFrameSource as AbstractFrameSource,
    CallableSource as CallableSource,
    CameraDevice as CameraDevice,
    find_camera as find_camera,
    FolderSource as FolderSource,
    Frame as Frame,
    list_cameras as list_cameras,
    Reconnect as Reconnect,
    SourceEvent as SourceEvent,
    VideoSource as VideoSource,
)
from ._controller import (
    CapController as CapController,
    CapRig as CapRig,
    plot_timeline as plot_timeline,
    run_cap_removal as run_cap_removal,
    Timeline as Timeline,
)
from ._ft import (
    AbstractForceTorqueSource as AbstractForceTorqueSource,
    ForceTorqueLog as ForceTorqueLog,
    netft_counts as netft_counts,
    NetFTSource as NetFTSource,
    open_ft_source as open_ft_source,
    UdpForceTorqueSource as UdpForceTorqueSource,
)
from ._gate import GateDecision as GateDecision, GateER as GateER
from ._group import (
    GRIP_UNAVAILABLE as GRIP_UNAVAILABLE,
    grip_wrench as grip_wrench,
    Mount as Mount,
    open_sensors as open_sensors,
    SensorGroup as SensorGroup,
)
from ._handle import open_sensor as open_sensor, SensorHandle as SensorHandle
from ._mcap import McapSink as McapSink, record_inversion as record_inversion, WRENCH_STATUSES as WRENCH_STATUSES
from ._pipeline import LiveSummary as LiveSummary, run_pipeline as run_pipeline
from ._records import RecordStream as RecordStream, WrenchFilter as WrenchFilter
from ._rectify import (
    calibrate_rectification as calibrate_rectification,
    detect_blobs as detect_blobs,
    load_rectification as load_rectification,
    order_grid as order_grid,
    Rectification as Rectification,
    save_rectification as save_rectification,
)
from ._rerun import RerunSink as RerunSink
from ._run import (
    capture_reference as capture_reference,
    format_summary as format_summary,
    make_colour_probe as make_colour_probe,
    make_gate as make_gate,
    make_tactile_processor as make_tactile_processor,
    open_source as open_source,
    parse_sink as parse_sink,
    run_live as run_live,
    schedule_script as schedule_script,
    SimulatedSensor as SimulatedSensor,
    TactileProcessor as TactileProcessor,
)
from ._sinks import (
    FileSink as FileSink,
    make_record as make_record,
    RECORD_VERSION as RECORD_VERSION,
    RecordingSink as RecordingSink,
    StreamSink as StreamSink,
    StripChart as StripChart,
    UdpSink as UdpSink,
    VideoRecorder as VideoRecorder,
    WrenchRecord as WrenchRecord,
)
from ._vision import (
    Classification as Classification,
    classify as classify,
    classify_patch as classify_patch,
    ColourMatch as ColourMatch,
    ColourProbe as ColourProbe,
    CONFIDENT_CNR as CONFIDENT_CNR,
    find_spectral_peaks as find_spectral_peaks,
    HUE_CLASSES as HUE_CLASSES,
    hue_histogram as hue_histogram,
    identify_colour as identify_colour,
    locate as locate,
    MoireNotch as MoireNotch,
    restore as restore,
    SeenObject as SeenObject,
    SeeThrough as SeeThrough,
    Sighting as Sighting,
    suppress_moire as suppress_moire,
    VisionClassifier as VisionClassifier,
)
