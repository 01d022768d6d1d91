"""Traffic on the registered video (the paper's purpose, beyond the paper): vehicles found
against the still background on the map, tracked (filterpy Kalman filter, Hungarian
assignment), smoothed forward and backward, with speeds in m/s from real frame times and metres
from the map, written as inD-style CSVs, GIS layers and a velocity field.

* :func:`run_traffic` does it all for a registration result (resumable).
* :class:`TrafficConfig` holds the settings.
"""

from registration.traffic.config import TrafficConfig
from registration.traffic.counts import (
    Crossing,
    SectionCounts,
    count_crossings,
    count_sections,
    write_counts_csvs,
)
from registration.traffic.detect import Detection, detect_vehicles
from registration.traffic.outputs import TrackRows, read_tracks_csv
from registration.traffic.runner import run_traffic
from registration.traffic.sequence import tracks_from_detections, usable_frames
from registration.traffic.timing import MetricFrame, frame_times, video_frame_times
from registration.traffic.track import SmoothTrack, smooth_track, track_detections

__all__ = [
    "Crossing",
    "SectionCounts",
    "count_crossings",
    "count_sections",
    "write_counts_csvs",
    "Detection",
    "MetricFrame",
    "SmoothTrack",
    "TrackRows",
    "TrafficConfig",
    "detect_vehicles",
    "frame_times",
    "read_tracks_csv",
    "run_traffic",
    "smooth_track",
    "track_detections",
    "tracks_from_detections",
    "usable_frames",
    "video_frame_times",
]
