"""Settings of the traffic stage (:class:`TrafficConfig`), with their units and reasons.

The paper stops at registered frames; its companion work (Rosten, Loveland & Hickman, "Automatic
creation of urban velocity fields from aerial video", 2009) tracks what moves on them. Nothing
here is the paper's, so the defaults are this project's, measured on the simulator's traffic and
the real NUST flyover (docs/traffic.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields


@dataclass(frozen=True)
class TrafficConfig:
    """How vehicles are found and tracked on the registered sequence.

    Attributes:
        cell_m: size of a pixel of the working grid on the map, metres. None = the frames' own
            ground resolution (one working pixel per frame pixel at the reference frame's
            centre), so nothing the camera resolved is lost and nothing is invented.
        background_span_s: the background of a frame is the per-pixel median of frames up to
            this long before and after it (s). A car 4.5 m long at 10 m/s covers a pixel for
            0.45 s, so it is one sample of the median, not its value.
        background_samples: frames sampled on each side within the span (evenly in time).
        min_samples: fewest samples a map pixel needs for a background (else no detection
            there: the edge of what the flight saw).
        tolerance_px: the background is compared as a local range (its minimum and maximum over
            this radius, working px): what registration leaves (relief, sub-pixel error) then
            does not look like motion.
        threshold_sigma: a pixel differs from the background when the difference passes this
            many robust noise sigmas (measured per frame) ...
        min_threshold_dn: ... and at least this many 8-bit levels (compression blocks) ...
        spread_factor: ... and at least this many times the background's own quartile spread
            over time there (relief that shifts as the camera flies on, trees in the wind).
        seed_factor: a blob must hold at least one pixel this many times over the threshold
            (hysteresis: the body of a car close to the road's colour stays attached to its
            strongly differing parts, noise alone does not start a blob). 1.5: on flights whose
            vehicles keep their distance, 29 of 101 separable vehicles missed in a default
            flight's frame differed by 1-1.8 times the threshold; 1.8 -> 1.5 raised MOTA by
            0.007-0.019 on the three simulated flights (positions 0.01-0.03 m worse), and on the
            real flyover kept the real car's track and lost the one false track.
        close_m: gaps up to this (metres) inside a blob are closed (windscreens, roof bars);
            below the 1.3-1.8 m between cars in neighbouring lanes.
        min_area_m2, max_area_m2: blob area of a vehicle, square metres (a motorbike's 1.5 to a
            bus's 40).
        max_length_m: longer blobs are not one vehicle.
        min_width_m: narrower blobs are edges (relief, registration), not vehicles.
        max_width_m: wider blobs are vehicles side by side that blur joined: they are cut at
            higher thresholds (:func:`~registration.traffic.detect.vehicle_pieces`).
        waist_min_length_m: a blob within one vehicle's limits but at least this long (metres)
            is looked at as two vehicles in a row (:func:`~registration.traffic.detect.waist_cut`)
            ...
        waist_ratio: ... and cut where it narrows to at most this share of the median width on
            either side ...
        waist_side_m: ... with at least this length (metres) on each side ...
        waist_balance: ... and the shorter side at least this share of the longer (two cars;
            a truck's windscreen band narrows its blob too, 2 : 5 of the way along). On the
            three simulated flights of ``bench traffic`` MOTA rose by 0.012, 0.009 and 0.001
            (default, paper-hard, long flight), speed RMSE moved by -0.06, +0.03 and -0.11 m/s;
            without the balance test trucks were cut at the windscreen (99 % of the new false
            detections on the long flight lay 2-4.5 m along a truck from its centre) and the
            long flight lost 0.005 in MOTA.
        join_shift_m: pieces of one vehicle whose pixels moved alike since a frame before
            (within this, metres) ...
        join_min_move_m: ... each by at least this (metres: things that stand still all move
            alike) ...
        join_lateral_m: ... whose centres lie within this (metres) of one line along that
            motion ...
        join_gap_m: ... with at most this (metres) between them along it, and together within
            one vehicle's limits, are one vehicle
            (:func:`~registration.traffic.detect.join_moving`): a truck whose roof is close to
            the road's colour shows as two to four blobs. On the default simulated flight of
            ``bench traffic``: MOTA 0.666 -> 0.693 with the join (docs/traffic.md).
        gate_m: a detection further than this (metres) from a track's prediction is not its ...
        gate_speed_mps: ... unless the track is new (one detection, no velocity yet) and a
            vehicle at this speed (m/s; 72 km/h) could have come further since: at the paper's
            5 frames/s its next detection may be 4 m on. Either way it must also lie within the
            prediction's own 99 % ellipse. Also how far a vehicle's pixels are looked for in
            the frame before (:func:`~registration.traffic.detect.motion_since`).
        velocity_gate_mps: a detection whose measured velocity (its pixels matched in a
            frame before) lies outside the 99 % ellipse of a track's predicted velocity, its
            uncertainty widened by this (m/s, 1 sigma), does not join that track: an oncoming
            or crossing vehicle's blob next to the prediction. On the three simulated flights of
            ``bench traffic`` ID switches 90 -> 72, 102 -> 87, 125 -> 115, speed RMSE 0.02-0.03
            m/s lower, MOTA +0.003 to +0.008; at 3 m/s alike, at 2 m/s tracks break (recall
            0.77 -> 0.60 on the default flight).
        max_gap_s: a track not seen for longer than this ends.
        min_hits: detections before a track counts (fewer = noise).
        min_travel_m: a track whose smoothed path ends less than this far from where it began
            is not a moving vehicle (parked cars shaken by registration, roof edges, trees).
        min_duration_s: a track shorter than this (s, first to last detection) is noise
            chained by chance (at 30 frames/s three detections span 0.07 s).
        min_speed_mps: a track slower than this on average is not moving traffic: roofs and
            trees whose relief shifts as the camera flies on (the real flyover: 1-2.5 m/s),
            pedestrians; a car crawling in a queue slower than this is lost too.
        max_speed_mps: a track whose smoothed speed ever passes this is not a vehicle in town
            (noise blobs chained into a track; 45 m/s is 162 km/h).
        min_observed: least share of the frames a track spans that it was detected in; a
            track seen less is mostly the filter coasting between detections chained by chance
            (the real flyover: one at 32 m/s seen in 8 of 32 frames).
        measurement_sigma_m: a detection's position noise for the tracker, metres: the part
            of a blob centre's error that changes from one frame to the next (0.39-0.40 m RMS
            per axis at 5 frames/s on the simulated flights, less at 30, where a blob changes
            little between frames; blur, a shadow's side, a windscreen cut off). Wider gates
            (0.45-0.55) tracked more of the simulated vehicles (MOTA +0.015 to +0.03) but let a
            known false track at the real flyover's edge back in.
        smooth_sigma_m: a detection's position noise for the forward-backward smoother,
            metres: the whole scatter of blob centres about the true ones, 0.55-0.60 m RMS per
            axis on the simulated flights (half of it stays from frame to frame: consecutive
            errors correlate by 0.49). Speeds 0.007-0.030 m/s closer than with 0.35.
        shift_sigma_m: the error of a vehicle's motion since a frame before measured by
            matching its pixels there (metres; 0.11 m median, 0.25 m 75th percentile on the
            default simulated flight, where its blob centres scatter by 0.8 m). A track begins
            at that velocity, and the smoother uses it where the track's blob centres confirm
            it (speed RMSE 0.643 -> 0.570 m/s on that flight) ...
        shift_gate_m: ... within this (metres over the time between the two frames).
        motion_baseline_s: a vehicle's pixels are matched in the latest usable frame at least
            this long before (s): the frame before at the paper's 5 frames/s, six frames back
            at 30, so that its motion is many times the match's error.
        end_detections: the first and last this many detections of a track that begins or
            ends inside the flight ...
        end_noise_factor: ... are trusted this many times less by the smoother
            (:func:`~registration.traffic.track.lost_end_noise`): the detector was losing its
            vehicle there. 2 and 8 lowered the speed RMSE by 0.12-0.13 m/s and the position
            RMSE by 0.014-0.021 m on the three simulated flights of ``bench traffic`` (MOTA
            -0.002 to +0.004); one detection at 8: speeds 0.09-0.11 m/s better. On the real
            flyover (30 frames/s, 2 detections = 0.07 s) the real car's speeds moved by at most
            0.25 m/s at its ends, none elsewhere.
        accel_sigma_mps2: how fast a vehicle's velocity may change while it is followed, m/s²
            per √s (the tracker's constant-velocity model: generous, so that a braking or
            turning vehicle stays within its gate).
        smooth_accel_sigma_mps2: how fast a vehicle's velocity wanders in the forward-backward
            smoother (m/s² per √s; constant-velocity model): town traffic's typical 1 m/s².
            Lower holds speeds steadier between noisy detections, most at a track's ends.
        field_cell_m: cell of the velocity field, metres.
        field_min_count: cells with fewer track points are left empty in the field.
    """

    cell_m: float | None = None
    background_span_s: float = 2.4
    background_samples: int = 6
    min_samples: int = 5
    tolerance_px: int = 1
    threshold_sigma: float = 5.0
    min_threshold_dn: float = 18.0
    spread_factor: float = 1.0
    seed_factor: float = 1.5
    close_m: float = 0.6
    min_area_m2: float = 1.5
    max_area_m2: float = 40.0
    max_length_m: float = 14.0
    min_width_m: float = 1.0
    max_width_m: float = 5.0
    waist_min_length_m: float = 7.0
    waist_ratio: float = 0.3
    waist_side_m: float = 3.0
    waist_balance: float = 0.6
    join_shift_m: float = 0.5
    join_min_move_m: float = 0.5
    join_lateral_m: float = 1.0
    join_gap_m: float = 3.0
    gate_m: float = 3.0
    gate_speed_mps: float = 20.0
    velocity_gate_mps: float = 4.0
    max_gap_s: float = 1.0
    min_hits: int = 3
    min_travel_m: float = 4.0
    min_duration_s: float = 1.0
    min_speed_mps: float = 2.0
    max_speed_mps: float = 45.0
    min_observed: float = 0.5
    measurement_sigma_m: float = 0.35
    smooth_sigma_m: float = 0.55
    shift_sigma_m: float = 0.2
    shift_gate_m: float = 2.5
    motion_baseline_s: float = 0.2
    end_detections: int = 2
    end_noise_factor: float = 8.0
    accel_sigma_mps2: float = 2.0
    smooth_accel_sigma_mps2: float = 1.0
    field_cell_m: float = 5.0
    field_min_count: int = 3

    def validate(self) -> None:
        """Raise a one-line ValueError naming the first bad value."""
        for f in fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise ValueError(f"traffic setting {f.name} must be a finite number, got {v!r}")
            if f.name == "tolerance_px":
                if not 0 <= v <= 5:
                    raise ValueError(f"traffic setting tolerance_px must be in 0..5, got {v}")
            elif f.name in ("min_observed", "waist_ratio", "waist_balance") and not 0 < v <= 1:
                raise ValueError(f"traffic setting {f.name} must be in (0, 1], got {v}")
            elif v <= 0:
                raise ValueError(f"traffic setting {f.name} must be positive, got {v}")
        if self.min_samples > 2 * self.background_samples:
            raise ValueError(
                f"traffic setting min_samples ({self.min_samples}) exceeds the frames sampled "
                f"(2 x background_samples = {2 * self.background_samples})"
            )
        if self.min_area_m2 >= self.max_area_m2:
            raise ValueError(
                f"traffic setting min_area_m2 ({self.min_area_m2}) must be below max_area_m2 "
                f"({self.max_area_m2})"
            )

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict) -> TrafficConfig:
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"unknown traffic setting(s): {', '.join(unknown)}")
        cfg = cls(**d)
        cfg.validate()
        return cfg
