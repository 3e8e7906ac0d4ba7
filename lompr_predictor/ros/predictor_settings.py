# SPDX-License-Identifier: Apache-2.0
"""The predictor node's parameters, as one frozen snapshot (`NodeBase.declare_settings`),
and its endpoints, whose topics are parameters."""

from __future__ import annotations

from dataclasses import dataclass, fields

from geometry_msgs.msg import PoseStamped, Vector3Stamped
from nav_msgs.msg import Path

from lompr_predictor.adaptation.scheduler import AdaptationSettings
from lompr_predictor.learning.model_file import check_sha256_text
from lompr_predictor.online.faults import StreamSettings
from lompr_predictor.online.guard import DEFAULT_GUARD, GuardSettings
from lompr_predictor.online.inference import Backend
from lompr_predictor.online.offset import CompensationLimits
from lompr_predictor.robot.chain import RobotSpec
from lompr_predictor.ros.node_base import (
    OUTPUT_QOS,
    SENSOR_INPUT_QOS,
    Endpoint,
    FrameSettings,
)
from lompr_predictor.ros.parameters import parameter
from lompr_predictor.ros.robot_description import DESCRIPTION_TOPIC_HELP
from lompr_predictor.scheduling import TRAINING_NICE
from lompr_predictor.stamps import GAP_FACTOR


@dataclass(frozen=True)
class PredictorCoreSettings(FrameSettings):
    """The parameters of the model, the inputs and the offset (after the shared
    `FrameSettings`)."""

    autostart: bool = parameter(
        True, 'configure and activate at start, so that a plain `ros2 run` predicts (a model '
        'that cannot be configured then stops the executable, exit code 2); false: start '
        'unconfigured and wait for a lifecycle manager (change_state)', read_only=True)
    model_path: str = parameter(
        '', 'TorchScript model file (lompr train); setting it at run time loads, checks and '
        'warms the new file and swaps it in, or keeps the running model and rejects the '
        'change with the reason')
    fallback_model_path: str = parameter(
        '', 'for a model that reads a reference preview: a model without one (same robot, '
        'horizon and sample period; verified like model_path, by its MODEL.sha256 file) that '
        'answers the samples the plan does not reach; empty: those samples get no offset',
        read_only=True)
    model_sha256: str = parameter(
        '', "if not empty, the sha256 the model file must have (the training report's "
        'model_sha256), checked on the bytes read before they are deserialised (a '
        'TorchScript file is code); takes precedence over the MODEL.sha256 file beside it',
        check=check_sha256_text)
    verify_model_hash: bool = parameter(
        True, 'refuse a model file whose bytes do not match model_sha256 or, if that is '
        'empty, the MODEL.sha256 file lompr train writes beside it; false (development '
        'only): load an unverified file', read_only=True)
    compensation_enabled: bool = parameter(
        False, 'true: publish the offset; false (every entry point starts so, until the site '
        'switches it on): shadow mode, predictions go on and every offset is zero')
    max_compensation: float = parameter(
        5e-4, 'largest offset [m] (XY norm); the offset is clamped to it', minimum=0.0,
        maximum=0.01)
    max_compensation_step: float = parameter(
        5e-5, 'largest change of the offset [m] (XY norm) from one sample to the next',
        minimum=0.0, maximum=0.01)
    compensation_bandwidth: float = parameter(
        15.0, 'cutoff [Hz] of the first-order low-pass the offset passes (0: none): a servo '
        'follows an offset only up to its bandwidth, and above it the plant error measured '
        'echoes the offset back into the prediction; keep it near the servo bandwidth',
        minimum=0.0, maximum=1000.0)
    robot_description_file: str = parameter(
        '', 'URDF of the robot (its calibrated geometry), the one the model must have been '
        "trained for: it gives the features' kinematics and its sha256 is checked; "
        'empty: robot_description_topic if set, else the packaged nominal LOMPR description',
        read_only=True)
    robot_description_topic: str = parameter(
        '', DESCRIPTION_TOPIC_HELP, read_only=True)
    base_frame: str = parameter(
        '', "the URDF frame the poses are in; empty: the model file's (the description's "
        'for the LOMPR)', read_only=True)
    tip_frame: str = parameter(
        '', "the URDF frame of the tool tip; empty: the model file's (the LOMPR's tool_tip)",
        read_only=True)
    sample_period: float = parameter(
        0.0, 'period [s] of the pose stamps, which the model must have been trained at '
        "(within 2 %); 0: the model file's", minimum=0.0, maximum=10.0, read_only=True)
    window: int = parameter(
        -1, "window length the model must have; -1: the model file's (a model swapped in at "
        "run time must keep the running one's)", minimum=-1, maximum=100_000, read_only=True)
    horizon: int = parameter(
        -1, "horizon [samples] the model must have (the controller's lead); -1: the model "
        "file's", minimum=-1, maximum=100_000, read_only=True)
    gap_factor: float = parameter(
        GAP_FACTOR, 'a stamp interval above this many sample periods is a gap (the trainer '
        'splits its data at the same one)', minimum=1.0, maximum=1000.0, read_only=True)
    min_interval_factor: float = parameter(
        0.5, "a stamp interval below this many sample periods means the input is not at the "
        "model's rate", minimum=0.0, maximum=1.0, read_only=True)
    stale_periods: float = parameter(
        5.0, 'no usable sample for this many sample periods: the input is stale and the '
        'offset is cancelled', minimum=1.0, maximum=1_000_000.0, read_only=True)
    stale_min_time: float = parameter(
        0.05, 'the input is stale only after at least this many seconds without a usable '
        'sample, whatever the rate: a process on a general-purpose OS stalls for '
        'milliseconds, many periods at kHz rates', minimum=0.0, maximum=3600.0,
        read_only=True)
    end_pose_topic: str = parameter('lompr/end_pose', 'PoseStamped measured tool tip input',
                                    read_only=True)
    reference_topic: str = parameter('lompr/reference', 'PoseStamped reference input',
                                     read_only=True)
    reference_preview_topic: str = parameter(
        'lompr/reference_preview', 'nav_msgs/Path input: the planned reference of the coming '
        'samples, subscribed only when the model reads a preview (lompr train --preview)',
        read_only=True)
    preview_tolerance: float = parameter(
        1e-5, 'distance [m] the commanded reference may lie from the preview planned for the '
        'same instant; further, the plan is dropped (the path changed) and the model waits '
        'for a window of rows with a new one', minimum=0.0, maximum=0.1, read_only=True)
    predicted_error_topic: str = parameter(
        'lompr/predicted_error', 'Vector3Stamped predicted X/Y error output', read_only=True)
    compensation_topic: str = parameter(
        'lompr/compensation', 'Vector3Stamped compensation offset output', read_only=True)
    inference_backend: str = parameter(
        'auto', 'what runs the network: onnxruntime (an ONNX graph exported from the verified '
        'model file at configure, used only if it agrees with TorchScript to 1e-6 relative on '
        'a warm-up batch; configure fails if it cannot serve), torchscript (the file as '
        'loaded), or auto (onnxruntime, else torchscript with the reason on /diagnostics)',
        choices=Backend, read_only=True)
    inference_threads: int = parameter(
        1, "torch threads, set by the executable's main() (process-wide); 1 keeps inference "
        'from contending with the executor', minimum=1, maximum=256, read_only=True)
    latency_samples: int = parameter(1000, 'last latencies kept for the p50/p99',
                                     minimum=10, maximum=1_000_000, read_only=True)
    accuracy_samples: int = parameter(1000, 'last predicted instants the live RMS is over',
                                      minimum=1, maximum=10_000_000, read_only=True)
    inference_time_warn: float = parameter(
        0.001, 'p99 inference time [s] above which the prediction status is WARN',
        minimum=1e-6, maximum=10.0)
    accuracy_warn: float = parameter(
        0.0, 'live RMS prediction error [m] (either axis) above which the prediction status '
        'is WARN (the machine has drifted from the model); 0: no such warning', minimum=0.0,
        maximum=1.0)
    warning_throttle_period: float = parameter(
        5.0, 'seconds between two warnings of the same kind', minimum=0.0, maximum=3600.0)
    status_hold: float = parameter(
        10.0, "seconds of the node's clock a problem that is over by itself (a refused "
        'model change, a failed write of the sample store, a failed adaptation attempt) '
        'keeps its status at WARN; then the status is back to OK and the problem one of its '
        'values', minimum=0.0, maximum=86_400.0)
    max_future_stamp: float = parameter(
        1.0, "an input stamped more than this many seconds ahead of the node's clock is "
        'dropped (not checked while the clock reads 0: sim time before the first /clock)',
        minimum=0.0, maximum=1e9, read_only=True)
    late_tolerance: float = parameter(
        0.005, "seconds an output may come after the instant it is for (on the node's "
        'clock: as stamped where the stamps are on it, else against the best-case input '
        'delay) before it is dropped as late; a '
        'sample whose inference could only finish late gets none', minimum=0.0,
        maximum=3600.0, read_only=True)

    def stream(self, sample_period: float) -> StreamSettings:
        """The rules the input stream is held to, at `sample_period` [s] (the model's, or
        the parameter's): every other field the parameter of the same name, so each is
        declared once, here."""
        return StreamSettings(sample_period=sample_period, **{
            item.name: getattr(self, item.name) for item in fields(StreamSettings)
            if item.name != 'sample_period'})

    @property
    def robot(self) -> RobotSpec:
        """The robot the model must run for (what it leaves open: the model file's)."""
        return RobotSpec(self.robot_description_file or None, self.base_frame, self.tip_frame)

    @property
    def limits(self) -> CompensationLimits:
        return CompensationLimits(self.max_compensation, self.max_compensation_step,
                                  self.compensation_enabled, self.compensation_bandwidth)


@dataclass(frozen=True)
class GuardParameters:
    """The live guard's parameters (`online.guard`)."""

    guard_enabled: bool = parameter(
        DEFAULT_GUARD.enabled,
        'the live guard: per axis, the model publishes only while its live RMS beats its '
        "fallbacks' on the same instants (its prior, what it predicts from the machine "
        'alone, and persistence, the plant error measured horizon samples before) and its '
        'inputs lie '
        'in the envelope it was trained on; else the better fallback answers there. false: '
        "the model always (the guard's status still says what it would do)")
    guard_window: float = parameter(
        DEFAULT_GUARD.window,
        'seconds of sample time the live RMS of the model, its prior and persistence are '
        'weighted over (exponentially): long enough to span what a program repeats (a '
        'model better on straights and worse at corners is judged on both)',
        minimum=0.001, maximum=86_400.0, read_only=True)
    guard_margin: float = parameter(
        DEFAULT_GUARD.margin,
        'relative margin (hysteresis): an axis goes to the better fallback as soon as the '
        "model's live RMS exceeds that fallback's, and back when the model is better by more "
        'than this fraction; the prior takes over from persistence when better by it too',
        minimum=0.0, maximum=0.9, read_only=True)
    guard_min_dwell: float = parameter(
        DEFAULT_GUARD.min_dwell,
        'seconds of sample time an axis stays with the model or a fallback before it '
        'may switch again', minimum=0.0, maximum=86_400.0, read_only=True)
    guard_min_scored: int = parameter(
        DEFAULT_GUARD.min_scored,
        'instants scored before the guard first judges the model (persistence answers '
        'until the model is better by the margin)', minimum=0,
        maximum=10_000_000, read_only=True)
    guard_envelope_fraction: float = parameter(
        DEFAULT_GUARD.envelope_fraction,
        "share of the recent feature rows outside the model's trained envelope (its "
        'metadata) above which the model is held back on both axes; 1: never for that',
        minimum=0.0, maximum=1.0, read_only=True)

    @property
    def guard(self) -> GuardSettings:
        """The live guard's rules: each the parameter `guard_` + its name."""
        return GuardSettings(**{item.name: getattr(self, f'guard_{item.name}')
                                for item in fields(GuardSettings)})


@dataclass(frozen=True)
class AdaptationParameters:
    """The sample store's and the online adaptation's parameters (`adaptation`)."""

    store_minutes: float = parameter(
        0.0, 'the sample store: the aligned samples of the last this many minutes of sample '
        'time (stamp, measured tool tip, reference, plant error: hence the compensation in '
        'force), in a ring preallocated at configure, 64 bytes a sample (3.84 MB a minute at '
        '1 kHz), which the service ~/write_samples (or store_write_at_shutdown) writes as a '
        'bag lompr train reads; 0: no store (unless adaptation_enabled: then the store holds '
        'adaptation_minutes, or this if longer)', minimum=0.0, maximum=60.0, read_only=True)
    store_folder: str = parameter(
        '', "where the sample store's bags are written, each a new directory "
        'samples-<UTC time>; empty: lompr_samples in $ROS_HOME (default ~/.ros)',
        read_only=True)
    store_write_at_shutdown: bool = parameter(
        False, 'write the sample store as a bag when the node lets it go (cleanup, shutdown, '
        'the process ending), by a process that finishes after the node')

    adaptation_enabled: bool = parameter(
        False, "online adaptation: every adaptation_period, a process below the node's "
        "priority (one torch thread) fine-tunes the model in force on the sample store's "
        'last adaptation_minutes, scores it on the newest held-out part against the model in '
        'force and persistence and, only if better than the model in force by '
        'adaptation_margin, writes it '
        'into adaptation_folder and swaps it in as a change of model_path would (verified by '
        'its pinned sha256); every attempt on /diagnostics and in adaptation.jsonl there. '
        'The store is sized for it (store_minutes)', read_only=True)
    adaptation_minutes: float = parameter(
        10.0, 'the data window: minutes of sample time an attempt learns from (its newest part, '
        "the trainer's test fraction, held out to score it); the first attempt waits until "
        'the store holds them',
        minimum=0.1, maximum=60.0, read_only=True)
    adaptation_period: float = parameter(
        600.0, "seconds of sample time (the node's clock: /clock under use_sim_time) between "
        'the starts of two attempts; an attempt still running delays the next',
        minimum=1.0, maximum=1e7, read_only=True)
    adaptation_margin: float = parameter(
        0.05, "relative: a candidate's held-out RMS must be at most (1 - margin) times the "
        "model in force's (persistence's is logged; the live guard covers a model worse "
        'than it)', minimum=0.0, maximum=0.9, read_only=True)
    adaptation_folder: str = parameter(
        '', 'where adapted models (adapted-<UTC time>-<n>.pt, sha256 beside) and the log '
        'adaptation.jsonl are written, one folder per node; empty: lompr_models in $ROS_HOME '
        '(default ~/.ros)', read_only=True)
    adaptation_keep: int = parameter(
        5, 'adapted models kept in adaptation_folder for a rollback (set model_path to one), '
        'the newest; older ones are deleted (never the one in force)', minimum=1,
        maximum=1000, read_only=True)
    adaptation_max_epochs: int = parameter(
        30, 'epochs of each fine-tuning at most (the validation-best kept)', minimum=1,
        maximum=10_000, read_only=True)
    adaptation_nice: int = parameter(
        TRAINING_NICE, "added to the attempt process's nice value: it leaves the cores to "
        'the node first (no effect under adaptation_idle)', minimum=0, maximum=19,
        read_only=True)
    adaptation_idle: bool = parameter(
        True, 'the attempt process runs under SCHED_IDLE (Linux): only on CPU time no other '
        'thread wants (where the cores are full, sched_fifo_priority keeps the nodes ahead); '
        'false: the normal policy, adaptation_nice below the node', read_only=True)

    @property
    def adaptation(self) -> AdaptationSettings:
        """The adaptation's settings: each the parameter `adaptation_` + its name."""
        return AdaptationSettings(**{item.name: getattr(self, f'adaptation_{item.name}')
                                     for item in fields(AdaptationSettings)})

    @property
    def kept_minutes(self) -> float:
        """The sample store's window [min]: store_minutes, at least the data window when
        adaptation is on (0: no store)."""
        if self.adaptation_enabled:
            return max(self.store_minutes, self.adaptation_minutes)
        return self.store_minutes


@dataclass(frozen=True)
class PredictorNodeSettings(AdaptationParameters, GuardParameters, PredictorCoreSettings):
    """The node's parameters, one field each, declared by `NodeBase.declare_settings` in
    this order: the shared `FrameSettings`, the core's, the guard's, the store's and the
    adaptation's."""


END_POSE = Endpoint('subscription', PoseStamped, 'end_pose_topic', SENSOR_INPUT_QOS,
                    'end pose')
REFERENCE = Endpoint('subscription', PoseStamped, 'reference_topic', SENSOR_INPUT_QOS,
                     'reference')
REFERENCE_PREVIEW = Endpoint('subscription', Path, 'reference_preview_topic', SENSOR_INPUT_QOS,
                             'reference preview (models with a preview only)')
PREDICTED_ERROR = Endpoint('publisher', Vector3Stamped, 'predicted_error_topic', OUTPUT_QOS,
                           'predicted error')
COMPENSATION = Endpoint('publisher', Vector3Stamped, 'compensation_topic', OUTPUT_QOS,
                        'compensation')
ENDPOINTS = (END_POSE, REFERENCE, REFERENCE_PREVIEW, PREDICTED_ERROR, COMPENSATION)
#: How to pin or skip the model hash, for a refusal message.
HASH_HINT = ('predictor_node: -p model_sha256:=<sha256>, or for development only '
             '-p verify_model_hash:=false')
#: How the fallback model is verified, for a refusal message (its own sidecar: `HASH_HINT`'s
#: model_sha256 pins model_path only).
FALLBACK_HASH_HINT = ('predictor_node: the fallback model is verified by its own sidecar '
                      '(model_sha256 pins model_path, not the fallback), or for development '
                      'only -p verify_model_hash:=false')
