"""The vehicle detector on planted frames of known content: a dark car with a few coloured
pixels, two cars that blur joins, two cars in a row joined by a narrow neck, a bus with a dark
windscreen, a burnt-in logo that moves over the map with the camera, a car moved by a known
fraction of a pixel since the frame before, and a truck seen as pieces that move together."""

from __future__ import annotations

import cv2
import numpy as np

from registration.traffic import TrafficConfig
from registration.traffic.background import (
    Background,
    WarpedFrame,
    WorkGrid,
    frame_keep_mask,
    warp_frame,
)
from registration.traffic.detect import Detection, detect_vehicles

CELL_M = 0.3  # metres per working pixel (one base px per working px)
ASPHALT = 80


def _detect(image, still, config=None, before=None, dt_s=0.2):
    """Detections of ``image`` against the still road ``still`` on a 1:1 grid at CELL_M;
    ``before``: the frame ``dt_s`` seconds before (the vehicles' motion is then measured)."""
    h, w = image.shape[:2]
    frame = WarpedFrame(1, image, np.ones((h, w), bool), (0, 0, w, h))
    count = np.full((h, w), 12, np.int32)
    background = Background(still, count, np.full((h, w), 2.0, np.float32), (0, 0, w, h))
    config = config or TrafficConfig()
    previous = None
    if before is not None:
        previous = WarpedFrame(0, before, np.ones((h, w), bool), (0, 0, w, h))
    return detect_vehicles(frame, background, WorkGrid(1.0, (w, h)), CELL_M, config, previous, dt_s)


def _road(rng, h=60, w=80):
    still = np.full((h, w, 3), ASPHALT, np.uint8)
    noisy = np.clip(still + rng.normal(0, 2, still.shape), 0, 255).astype(np.uint8)
    return still, noisy


def test_a_dark_car_with_a_few_coloured_pixels_is_one_vehicle(rng):
    # A black car, 4.5 x 1.8 m (15 x 6 px), with a 2 x 3 px stripe that is not shadow-coloured
    # (a reflection on its roof): the stripe is too small to be a car, and the dark pixels
    # around it are the car, not its shadow.
    still, image = _road(rng)
    image[27:33, 30:45] = (25, 25, 28)
    image[29:31, 36:39] = (40, 140, 160)
    dets = _detect(image, still)
    assert len(dets) == 1, dets
    # Centre of the 15 x 6 px body: (37, 29.5) px.
    assert np.hypot(dets[0].x - 37.0, dets[0].y - 29.5) * CELL_M < 0.3, dets[0]
    assert 3.6 < dets[0].length_m < 5.4 and 1.2 < dets[0].width_m < 2.4, dets[0]


def test_a_white_car_with_its_shadow_is_one_vehicle_at_the_cars_centre(rng):
    # A white car with its shadow is one vehicle at the car's centre: the shadow does not pull
    # it (the rule above must not turn a real car's shadow into a second vehicle).
    still, image = _road(rng)
    image[27:33, 30:45] = (235, 235, 235)
    image[33:36, 32:47] = (28, 28, 32)  # its shadow, cast down and right
    dets = _detect(image, still)
    assert len(dets) == 1, dets
    assert np.hypot(dets[0].x - 37.0, dets[0].y - 29.5) * CELL_M < 0.3, dets[0]


def test_cars_side_by_side_that_blur_joins_are_cut_apart(rng):
    # Two white cars in neighbouring lanes, 1.2 m (4 px) apart, blurred (sigma 1.5 px) so the
    # gap between them differs from the road by more than the threshold: one blob ~6 m wide.
    still, sharp = _road(rng)
    image = still.copy()
    image[20:26, 30:45] = 235
    image[30:36, 31:46] = 235
    image = cv2.GaussianBlur(image, (0, 0), 1.5)
    image = np.clip(image + rng.normal(0, 2, image.shape), 0, 255).astype(np.uint8)
    dets = sorted(_detect(image, still), key=lambda d: d.y)
    assert len(dets) == 2, dets
    for d, (cx, cy) in zip(dets, [(37.0, 22.5), (38.0, 32.5)], strict=True):
        assert np.hypot(d.x - cx, d.y - cy) * CELL_M < 0.4, d
        assert d.width_m < 3.5, d


def _white_car(image, y0, x0, length_px=15, width_px=6):
    image[y0 : y0 + width_px, x0 : x0 + length_px] = (235, 235, 235)


def test_a_car_with_a_hole_in_its_blob_is_at_its_outlines_centre(rng):
    # A white car of 15 x 6 px whose rear window (6 x 4 px, inside the outline) is the road's
    # colour: its blob has a hole the closing does not fill. The pixels' mean lies 1.3 px
    # (0.38 m) towards the front; the vehicle is at the centre of its outline.
    still, image = _road(rng)
    _white_car(image, 27, 30)
    image[28:32, 31:37] = ASPHALT
    (det,) = _detect(image, still)
    assert np.hypot(det.x - 37.0, det.y - 29.5) * CELL_M < 0.1, det
    blob = np.zeros(image.shape[:2], bool)
    blob[27:33, 30:45] = True
    blob[28:32, 31:37] = False
    ys, xs = np.nonzero(blob)
    assert (xs.mean() - 37.0) * CELL_M > 0.3  # what the mean would give


def test_two_cars_in_a_row_joined_by_a_narrow_neck_are_two_vehicles(rng):
    # Two white cars of 4.5 x 1.8 m (15 x 6 px) in one lane, 2.1 m (7 px) apart, joined by a
    # strip one pixel wide (what blur and a shadow leave in the gap): one blob 11 m long, within
    # a bus's limits. It narrows to 1 px of 6 at the gap: two vehicles at the cars' centres.
    still, image = _road(rng, w=100)
    _white_car(image, 27, 20)
    _white_car(image, 27, 42)
    image[30, 35:42] = (200, 200, 200)
    dets = sorted(_detect(image, still), key=lambda d: d.x)
    assert len(dets) == 2, dets
    for d, cx in zip(dets, (27.0, 49.0), strict=True):
        assert np.hypot(d.x - cx, d.y - 29.5) * CELL_M < 0.3, d
        assert 3.6 < d.length_m < 6.3, d  # a car and at most half the gap
    # Without the cut (the rule switched off by its length) it is one vehicle between them.
    off = TrafficConfig(waist_min_length_m=TrafficConfig().max_length_m + 1)
    (one,) = _detect(image, still, off)
    assert abs(one.x - 38.0) < 1.0 and one.length_m > 10.0, one


def test_a_bus_whose_windscreen_narrows_its_blob_is_one_vehicle(rng):
    # A white bus of 10.5 x 2.4 m (35 x 8 px) whose dark windscreen, 1.8 m long and as dark as
    # the road, spans its width but for one pixel on each side: its blob narrows to 2 px of 8
    # there, 2 : 5 of the way along. The two sides are a bus's front and back, not two cars.
    still, image = _road(rng)
    image[20:28, 20:55] = (235, 235, 235)
    image[21:27, 41:47] = ASPHALT
    (bus,) = _detect(image, still)
    assert np.hypot(bus.x - 37.0, bus.y - 23.5) * CELL_M < 0.4 and bus.length_m > 9.5, bus
    # It is the balance test that keeps it whole.
    assert len(_detect(image, still, TrafficConfig(waist_balance=0.3))) == 2


class _Identity:
    """A result whose frames lie on the base pixel for pixel, with a logo box in its config."""

    def __init__(self, size, boxes):
        self.frame_size = self.base_size = size
        self.config = {"adjust": {"probes": {"exclude": boxes}}}

    def frame_to_base(self, k, xy, stage="local"):
        return np.asarray(xy, np.float64).reshape(-1, 2)

    def base_to_frame(self, k, xy, stage="local", *, clip=True):
        return self.frame_to_base(k, xy, stage)


def test_a_burnt_in_logo_is_not_looked_at(rng):
    result = _Identity((80, 60), [[10.0, 5.0, 30.0, 20.0]])
    keep = frame_keep_mask(result)
    assert keep[5:20, 10:30].max() == 0 and keep[25:, 35:].min() == 255
    frame = rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)
    w = warp_frame(result, 0, frame, WorkGrid(1.0, (80, 60)), frame_keep=keep)
    assert not w.mask[6:19, 11:29].any()
    assert w.mask[25:55, 35:75].all()
    # Without the box nothing inside is left out.
    assert frame_keep_mask(_Identity((80, 60), [])) is None


def test_the_noise_sigma_is_the_median_absolute_grey_difference(rng):
    """1.4826 x the median of |grey(frame) - grey(background)| over the valid pixels, as numpy's
    median gives it (the two middle values' mean for an even count), on random images and
    masks of odd and even size."""
    from registration.traffic.background import noise_sigma

    sizes = [(1, 1), (1, 2), (3, 5), (40, 31), (64, 64)]
    for h, w in sizes:
        for share in (0.1, 0.5, 1.0):
            a = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            b = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            valid = rng.random((h, w)) < share
            valid.flat[0] = True
            grey = [cv2.cvtColor(x, cv2.COLOR_BGR2GRAY).astype(float) for x in (a, b)]
            expected = 1.4826 * np.median(np.abs(grey[0] - grey[1])[valid])
            assert noise_sigma(a, b, valid) == expected, (h, w, share)
    assert noise_sigma(a, b, np.zeros((h, w), bool)) == 0.0


def _textured_car(rng, length_px=15, width_px=6, upscale=4):
    """A car's top view with some pattern (roof, windows), ``upscale`` times finer than the
    working grid."""
    car = np.empty((width_px * upscale, length_px * upscale, 3), np.uint8)
    car[:] = (200, 60, 50)
    car[:, int(0.6 * car.shape[1]) : int(0.8 * car.shape[1])] = (40, 30, 30)  # windscreen
    car[upscale:-upscale, upscale * 3 : upscale * 7] = (230, 120, 110)  # roof light
    return car


def _scene(rng, cars, h=60, w=100, upscale=4):
    """The road with ``cars`` pasted at ``(x, y)`` working px (multiples of 1/upscale), drawn
    ``upscale`` times finer and averaged down: positions that are fractions of a pixel."""
    fine = np.full((h * upscale, w * upscale, 3), ASPHALT, np.uint8)
    for (x, y), car in cars:
        x0, y0 = int(round(x * upscale)), int(round(y * upscale))
        fine[y0 : y0 + car.shape[0], x0 : x0 + car.shape[1]] = car
    image = cv2.resize(fine, (w, h), interpolation=cv2.INTER_AREA)
    noise = rng.normal(0, 1.5, image.shape)
    return np.clip(image + noise, 0, 255).astype(np.uint8)


def test_a_cars_motion_since_the_frame_before_is_measured_to_a_fraction_of_a_pixel(rng):
    # A car moved by (3, -2) px plus every quarter pixel in x and y (0.9-1.2 m, 0.3-0.6 m in
    # 0.2 s), drawn at quarter pixels: its pixels matched in the frame before give the shift
    # to 0.1-0.15 px RMS (measured: 0.09 / 0.14, worst 0.21), where the centres of two blobs
    # differ by their outlines too.
    car = _textured_car(rng)
    still = np.full((60, 100, 3), ASPHALT, np.uint8)
    errors = []
    for fx in (0.0, 0.25, 0.5, 0.75):
        for fy in (0.0, 0.25, 0.5, 0.75):
            before = _scene(rng, [((40.0, 28.0), car)])
            image = _scene(rng, [((43.0 + fx, 26.0 + fy), car)])
            (det,) = _detect(image, still, before=before)
            errors.append((det.shift_x - (3.0 + fx), det.shift_y - (-2.0 + fy)))
    errors = np.array(errors)
    assert np.sqrt(np.mean(errors**2, axis=0)).max() < 0.2, errors
    assert np.abs(errors).max() < 0.3, errors
    # Without the frame before there is no shift; the same detection otherwise.
    (alone,) = _detect(image, still)
    assert np.isnan(alone.shift_x) and np.isnan(alone.shift_y)
    assert (alone.x, alone.y, alone.length_m) == (det.x, det.y, det.length_m)
    # Faster than the reach (gate_speed_mps over the frame interval: 4 m, 13.3 px): none.
    far = _scene(rng, [((40.0 + 16.0, 28.0), car)])
    (fast,) = _detect(far, still, before=before)
    assert np.isnan(fast.shift_x), fast


def test_a_detections_unmeasured_shift_is_null_in_json():
    d = Detection(3, 10.5, 20.25, 4.5, 1.8, 90.0, 8.1, 2.5)
    doc = d.to_dict()
    assert doc["shift_x"] is None and doc["shift_y"] is None
    back = Detection.from_dict(doc)
    assert np.isnan(back.shift_x) and (back.k, back.x, back.contrast) == (3, 10.5, 2.5)
    moved = Detection(3, 10.5, 20.25, 4.5, 1.8, 90.0, 8.1, 2.5, 1.23456, -0.5)
    assert Detection.from_dict(moved.to_dict()).shift_x == 1.2346
    # A file of the release before (no shift keys) reads as unmeasured.
    old = {k: v for k, v in doc.items() if not k.startswith("shift")}
    assert np.isnan(Detection.from_dict(old).shift_y)


def _truck(length_px=37, width_px=8):
    """A truck whose roof is the road's colour: only its cab (white), a roof box (white) and
    its rear (light grey) differ from the road, 2.1 m (7 px) apart: three blobs."""
    truck = np.full((width_px, length_px, 3), ASPHALT, np.uint8)
    truck[:, 31:37] = (235, 235, 235)  # cab, 1.8 m
    truck[1:-1, 17:24] = (220, 220, 220)  # roof box, 2.1 m
    truck[:, 0:10] = (180, 180, 190)  # rear doors, 3 m
    return truck


def test_a_truck_seen_as_pieces_that_move_together_is_one_vehicle(rng):
    # The truck drives 8 px (2.4 m, 12 m/s at 5 frames/s) along +x. Alone, a frame shows its
    # three pieces as three vehicles; with the frame before, the pieces moved alike and lie in
    # line with 2.1 m between them: one vehicle of the truck's length at its centre.
    truck = _truck()
    still = np.full((60, 100, 3), ASPHALT, np.uint8)
    before = _scene(rng, [((30.0, 26.0), np.repeat(np.repeat(truck, 4, 0), 4, 1))])
    image = _scene(rng, [((38.0, 26.0), np.repeat(np.repeat(truck, 4, 0), 4, 1))])
    assert len(_detect(image, still)) == 3
    (one,) = _detect(image, still, before=before)
    # The truck spans x 38..75, y 26..34 px: centre (56, 29.5).
    assert np.hypot(one.x - 56.0, one.y - 29.5) * CELL_M < 0.4, one
    assert 10.0 < one.length_m < 12.0, one
    assert abs(one.shift_x - 8.0) < 0.2 and abs(one.shift_y) < 0.2, one
    # Joined only within join_gap_m: with 1.5 m allowed the 2.1 m gaps keep them apart.
    assert len(_detect(image, still, TrafficConfig(join_gap_m=1.5), before=before)) == 3


def test_two_cars_in_a_row_at_one_speed_stay_two_vehicles(rng):
    # Two cars in one lane at the same 12 m/s, 1 s apart (12 m between them, 40 px): they move
    # exactly alike but further apart than a vehicle's pieces.
    car = _textured_car(rng)
    still = np.full((60, 140, 3), ASPHALT, np.uint8)
    cars = lambda dx: [((10.0 + dx, 26.0), car), ((65.0 + dx, 26.0), car)]  # noqa: E731
    before, image = _scene(rng, cars(0.0), w=140), _scene(rng, cars(8.0), w=140)
    dets = sorted(_detect(image, still, before=before), key=lambda d: d.x)
    assert len(dets) == 2, dets
    for d, cx in zip(dets, (25.0, 80.0), strict=True):
        assert np.hypot(d.x - cx, d.y - 28.5) * CELL_M < 0.4, d
        assert abs(d.shift_x - 8.0) < 0.2, d
