"""Tests of the irmosaic Python module on a small flight written by `irmosaic synth`.

Run by ctest (python_bindings) with PYTHONPATH at the built module and IRMOSAIC_CLI at the CLI.
"""
import csv
import json
import os
import subprocess

import numpy as np
import pytest
from osgeo import gdal

import irmosaic

gdal.UseExceptions()

FRAMES = 16


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """A 16-frame simulated sweep flight (frames/, pos.csv, camera.json, truth.json)."""
    out = tmp_path_factory.mktemp("flight")
    cli = os.environ.get("IRMOSAIC_CLI", "irmosaic")
    config = out.parent / "synth.json"
    config.write_text('{"origin_lat_deg": 47.2, "origin_lon_deg": 8.5}')
    subprocess.run([cli, "synth", "--config", str(config), "--out", str(out),
                    "--frames", str(FRAMES), "--seed", "3"],
                   check=True, capture_output=True)
    return out


def read_frames(flight_dir):
    """(index, time_s, uint16 image) of every frame listed in frames.csv."""
    frames = []
    with open(flight_dir / "frames.csv") as f:
        for row in csv.DictReader(f):
            ds = gdal.Open(str(flight_dir / row["file"]))
            frames.append((int(row["index"]), float(row["time_s"]), ds.ReadAsArray()))
    return frames


def apply_h(h, x, y):
    p = h @ np.array([x, y, 1.0])
    return p[:2] / p[2]


@pytest.fixture(scope="module")
def run(flight, tmp_path_factory):
    """The flight mosaicked on the truth's grid: (mosaicker, truth, push results, store path)."""
    truth = json.loads((flight / "truth.json").read_text())
    store = str(tmp_path_factory.mktemp("run") / "f.irmosaic")
    options = irmosaic.MosaickerOptions(store)
    options.origin_lat_deg = truth["origin"]["lat_deg"]
    options.origin_lon_deg = truth["origin"]["lon_deg"]
    options.gsd_m = truth["gsd_m"]
    camera = irmosaic.CameraModel.load_json(str(flight / "camera.json"))
    pos = irmosaic.PosTrack.load_csv(str(flight / "pos.csv"))
    m = irmosaic.Mosaicker(options, camera, pos)
    results = [m.push(i, t, img) for i, t, img in read_frames(flight)]
    m.finish()
    return m, truth, results, store


def test_camera_and_pos_load(flight):
    camera = irmosaic.CameraModel.load_json(str(flight / "camera.json"))
    assert (camera.width, camera.height) == (640, 512)
    assert camera.fx == pytest.approx(2400.0)
    pos = irmosaic.PosTrack.load_csv(str(flight / "pos.csv"))
    assert len(pos) == FRAMES
    # Records round-trip through dicts; the pose between two samples lies between them.
    rebuilt = irmosaic.PosTrack.from_records(pos.records(), source="copy")
    assert rebuilt.records() == pos.records()
    r0, r1 = pos.records()[0], pos.records()[1]
    mid = pos.pose_at(0.5 * (r0["time_s"] + r1["time_s"]))
    assert min(r0["lat_deg"], r1["lat_deg"]) <= mid["lat_deg"] <= max(r0["lat_deg"], r1["lat_deg"])
    assert pos.pose_at(r0["time_s"] - 10.0) is None


def test_every_frame_placed_close_to_truth(run):
    m, truth, results, _ = run
    assert all(r["placed"] for r in results), [r["reason"] for r in results]
    summary = m.summary()
    assert summary["frames_placed"] == FRAMES
    assert summary["gsd_m"] == pytest.approx(truth["gsd_m"])
    placements = m.placements()
    assert [p["index"] for p in placements] == list(range(FRAMES))
    true_h = {f["index"]: np.array(f["mosaic_from_image"], dtype=float).reshape(3, 3) for f in truth["frames"]}
    errors, pos_errors = [], []
    for p in placements:
        h = p["mosaic_from_image"]
        assert isinstance(h, np.ndarray) and h.shape == (3, 3)
        assert p["residual_px"] >= 0.0 and p["inliers"] >= 0
        centre = apply_h(true_h[p["index"]], 319.5, 255.5)
        errors.append(np.linalg.norm(apply_h(h, 319.5, 255.5) - centre))
        pos_errors.append(np.linalg.norm(apply_h(p["pos_mosaic_from_image"], 319.5, 255.5) - centre))
    print("centre error px: median %.2f max %.2f (POS only: median %.2f)" %
          (np.median(errors), np.max(errors), np.median(pos_errors)))
    assert summary["frames_registered"] >= FRAMES // 2
    # POS errors (2 m, 0.3 deg, 1 sigma, at 800 m) put frames ~19 px (0.33 m px) off; the
    # registered, fused placements must do clearly better (measured: median 7.8 px).
    assert np.median(errors) < 12.0
    assert np.median(errors) < 0.7 * np.median(pos_errors)


def test_read_window_matches_published_store(run):
    m, truth, _, store = run
    col, row, width, height = m.bounds()
    assert width > 0 and height > 0
    image, coverage, gt, wkt = m.read_window(col, row, width, height)
    assert image.dtype == np.uint16 and image.shape == (height, width)
    assert coverage.dtype == np.uint8 and coverage.shape == (height, width)
    assert set(np.unique(coverage)) <= {0, 255}
    # Bounds are whole 512-px tiles around an oblique sweep's fan: a fair part stays empty.
    assert (coverage > 0).mean() > 0.1
    gsd = truth["gsd_m"]
    assert gt == pytest.approx(((col - 0.5) * gsd, gsd, 0.0, -(row - 0.5) * gsd, 0.0, -gsd))
    assert "PROJCRS" in wkt or "PROJCS" in wkt
    # GDAL reads the same pixels from the published store at the same georeferenced place.
    ds = gdal.Open(os.path.join(store, "mosaic.vrt"))
    vgt = ds.GetGeoTransform()
    x0 = round((gt[0] - vgt[0]) / vgt[1])
    y0 = round((gt[3] - vgt[3]) / vgt[5])
    assert x0 >= 0 and y0 >= 0
    band = ds.GetRasterBand(1).ReadAsArray(x0, y0, width, height)
    covered = coverage > 0
    assert np.array_equal(band[covered], image[covered])


# Bad input: clear Python errors carrying the library's messages.

@pytest.fixture
def small(tmp_path, flight):
    camera = irmosaic.CameraModel.load_json(str(flight / "camera.json"))
    pos = irmosaic.PosTrack.load_csv(str(flight / "pos.csv"))
    return irmosaic.Mosaicker(irmosaic.MosaickerOptions(str(tmp_path / "s.irmosaic")), camera, pos)


def test_wrong_dtype_raises_type_error(small):
    with pytest.raises(TypeError, match="uint16"):
        small.push(0, 0.0, np.zeros((512, 640), dtype=np.int32))


def test_wrong_shape_raises_value_error(small):
    with pytest.raises(ValueError, match="2-D"):
        small.push(0, 0.0, np.zeros((512, 640, 3), dtype=np.uint8))


def test_non_contiguous_raises_value_error(small):
    image = np.zeros((512, 1280), dtype=np.uint16)[:, ::2]
    with pytest.raises(ValueError, match="contiguous"):
        small.push(0, 0.0, image)


def test_not_an_array_raises_type_error(small):
    with pytest.raises(TypeError):
        small.push(0, 0.0, [[1, 2], [3, 4]])


def test_bad_frames_are_skipped_with_a_reason(small, flight):
    first = irmosaic.PosTrack.load_csv(str(flight / "pos.csv")).records()[0]["time_s"]
    wrong_size = small.push(0, first, np.zeros((100, 100), dtype=np.uint16))
    assert not wrong_size["placed"] and wrong_size["reason"]
    before = small.push(1, first - 100.0, np.zeros((512, 640), dtype=np.uint16))
    assert not before["placed"] and before["reason"]
    assert small.summary()["frames_skipped"] == 2


def test_read_window_before_any_frame_raises(small):
    with pytest.raises(RuntimeError, match="no frame"):
        small.read_window(0, 0, 10, 10)


def test_missing_pos_field_names_it():
    record = {"time_s": 0.0, "lat_deg": 47.0, "lon_deg": 8.0, "height_m": 800.0,
              "roll_deg": 0.0, "pitch_deg": 0.0}
    with pytest.raises(KeyError, match="yaw_deg"):
        irmosaic.PosTrack.from_records([record])
    with pytest.raises(TypeError, match="not a number"):
        irmosaic.PosTrack.from_records([dict(record, yaw_deg="north")])


def test_library_input_errors_are_value_errors(tmp_path):
    with pytest.raises(irmosaic.InputError) as info:
        irmosaic.PosTrack.load_csv(str(tmp_path / "missing.csv"))
    assert isinstance(info.value, ValueError)
    assert "missing.csv" in str(info.value)
    bad = tmp_path / "pos.csv"
    bad.write_text("time_s,lat_deg,lon_deg,height_m,roll_deg,pitch_deg,yaw_deg\n"
                   "0.0,47.0,8.0,800,0,0,0\n0.04,147.0,8.0,800,0,0,0\n")
    with pytest.raises(ValueError, match="lat_deg"):
        irmosaic.PosTrack.load_csv(str(bad))
    records = [{"time_s": 1.0, "lat_deg": 47.0, "lon_deg": 8.0, "height_m": 800.0,
                "roll_deg": 0.0, "pitch_deg": 0.0, "yaw_deg": 0.0}] * 2
    with pytest.raises(irmosaic.InputError, match="time"):
        irmosaic.PosTrack.from_records(records, source="mylog")


def test_bad_options(tmp_path, flight):
    with pytest.raises(ValueError, match="mode"):
        irmosaic.MosaickerOptions(str(tmp_path / "x"), mode="append")
    options = irmosaic.MosaickerOptions(str(tmp_path / "x"))
    options.gsd_m = -1.0
    with pytest.raises(ValueError):
        options.validate()
    camera = irmosaic.CameraModel.load_json(str(flight / "camera.json"))
    pos = irmosaic.PosTrack.load_csv(str(flight / "pos.csv"))
    with pytest.raises(irmosaic.InputError):
        irmosaic.Mosaicker(options, camera, pos)


def test_unwritable_store_raises_output_error(flight):
    camera = irmosaic.CameraModel.load_json(str(flight / "camera.json"))
    pos = irmosaic.PosTrack.load_csv(str(flight / "pos.csv"))
    # /proc refuses new folders even to root; the store opens at the first placed frame.
    m = irmosaic.Mosaicker(irmosaic.MosaickerOptions("/proc/irmosaic/s.irmosaic"), camera, pos)
    index, time_s, image = read_frames(flight)[0]
    with pytest.raises(irmosaic.OutputError) as info:
        m.push(index, time_s, image)
    assert isinstance(info.value, OSError)
    assert "/proc/irmosaic" in str(info.value)


# The rest of the library API: poses pushed directly, published generations, frame records.

def test_frame_records_match_the_placements(run):
    m, truth, _, _ = run
    records = m.frame_records()
    placements = {p["index"]: p for p in m.placements()}
    assert [r["index"] for r in records] == list(range(FRAMES))
    gsd = truth["gsd_m"]
    corners = [(-0.5, -0.5), (639.5, -0.5), (639.5, 511.5), (-0.5, 511.5)]
    for r in records:
        p = placements[r["index"]]
        assert r["footprint_m"].shape == (4, 2)
        assert r["status"] == ("pos_only" if p["pos_only"] else "registered")
        assert r["pos_only"] == p["pos_only"]
        # The footprint is the placement's corners on the plane (x = col*gsd, y = -row*gsd) as
        # of the frame's last render, which lags the placement by < rerender_threshold_px.
        for k, (x, y) in enumerate(corners):
            col, row = apply_h(p["mosaic_from_image"], x, y)
            error_px = np.linalg.norm(r["footprint_m"][k] - (col * gsd, -row * gsd)) / gsd
            assert error_px < 0.26, (r["index"], k, error_px)


def test_poses_pushed_directly_need_no_pos_track(run, flight, tmp_path):
    tracked, truth, results, _ = run
    camera = irmosaic.CameraModel.load_json(str(flight / "camera.json"))
    records = irmosaic.PosTrack.load_csv(str(flight / "pos.csv")).records()
    options = irmosaic.MosaickerOptions(str(tmp_path / "posed.irmosaic"))
    with pytest.raises(irmosaic.InputError, match="origin_lat_deg, origin_lon_deg and gsd_m"):
        irmosaic.Mosaicker(options, camera)
    options.origin_lat_deg = truth["origin"]["lat_deg"]
    options.origin_lon_deg = truth["origin"]["lon_deg"]
    options.gsd_m = truth["gsd_m"]
    m = irmosaic.Mosaicker(options, camera)  # no POS track: poses come with the frames
    frames = read_frames(flight)[:4]
    for (index, time_s, image), record in zip(frames, records):
        pose = {k: v for k, v in record.items() if k != "time_s"}
        r = m.push(index, time_s, image, pose=pose)
        assert r["placed"], r["reason"]
        # The same POS prediction as the track's (sampled at the frame time), to 1e-3 px.
        expected = results[index]["placement"]["pos_mosaic_from_image"]
        for x, y in [(0.0, 0.0), (639.0, 511.0)]:
            assert np.linalg.norm(apply_h(r["placement"]["pos_mosaic_from_image"], x, y) -
                                  apply_h(expected, x, y)) < 1e-3
    with pytest.raises(KeyError, match="yaw_deg"):
        m.push(9, 0.0, frames[0][2], pose={"lat_deg": 47.2, "lon_deg": 8.5, "height_m": 800.0,
                                           "roll_deg": 0.0, "pitch_deg": 0.0})
    broken = dict(records[0], lat_deg=float("nan"))
    skipped = m.push(9, 0.0, frames[0][2], pose=broken)
    assert not skipped["placed"] and "pose is not finite" in skipped["reason"]
    m.finish()
    assert m.summary()["frames_placed"] == 4


def test_published_generations_reach_the_callback(flight, tmp_path):
    camera = irmosaic.CameraModel.load_json(str(flight / "camera.json"))
    pos = irmosaic.PosTrack.load_csv(str(flight / "pos.csv"))
    options = irmosaic.MosaickerOptions(str(tmp_path / "g.irmosaic"))
    options.publish_interval_s = 0.001
    m = irmosaic.Mosaicker(options, camera, pos)
    assert m.published_generation() == 0
    with pytest.raises(TypeError, match="callable"):
        m.on_published(42)
    generations = []
    m.on_published(generations.append)
    for index, time_s, image in read_frames(flight)[:4]:
        assert m.push(index, time_s, image)["placed"]
    m.request_publish()
    m.wait_published(m.published_generation() + 1)
    assert m.published_generation() >= 1
    m.finish()
    assert generations, "no generation reported"
    assert generations == sorted(set(generations))
    assert generations[-1] == m.published_generation() == m.summary()["generations_published"]
    # The published store is what GDAL reads: its frames.gpkg has the four frames.
    ds = gdal.OpenEx(str(tmp_path / "g.irmosaic" / "frames.gpkg"), gdal.OF_VECTOR)
    assert ds.GetLayer(0).GetFeatureCount() == 4


def test_callback_errors_propagate(flight, tmp_path):
    camera = irmosaic.CameraModel.load_json(str(flight / "camera.json"))
    pos = irmosaic.PosTrack.load_csv(str(flight / "pos.csv"))
    m = irmosaic.Mosaicker(irmosaic.MosaickerOptions(str(tmp_path / "e.irmosaic")), camera, pos)
    index, time_s, image = read_frames(flight)[0]
    assert m.push(index, time_s, image)["placed"]
    m.on_published(lambda generation: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        m.finish()  # the final publish always reports a new generation


def test_invalid_tile_size_is_refused_with_its_name(tmp_path, flight):
    camera = irmosaic.CameraModel.load_json(str(flight / "camera.json"))
    pos = irmosaic.PosTrack.load_csv(str(flight / "pos.csv"))
    options = irmosaic.MosaickerOptions(str(tmp_path / "t.irmosaic"))
    options.tile_size = 100
    with pytest.raises(irmosaic.InputError, match="tile_size 100"):
        irmosaic.Mosaicker(options, camera, pos)
    options.tile_size = 512
    options.compression = "JPEG"
    with pytest.raises(irmosaic.InputError, match="compression"):
        irmosaic.Mosaicker(options, camera, pos)
    assert not (tmp_path / "t.irmosaic").exists()


def test_background_priorities_are_options_checked_by_name(tmp_path):
    options = irmosaic.MosaickerOptions(str(tmp_path / "p.irmosaic"))
    assert options.writer_nice == 5
    assert options.tune_heap is True
    assert options.fusion.optimizer_nice == 0
    assert options.fusion.max_output_backlog_s == 0.25
    assert options.fusion.rerender_settled_frames is False
    options.fusion.optimizer_nice = 10
    options.fusion.max_output_backlog_s = 0.0
    options.writer_nice = 0
    options.validate()
    options.fusion.optimizer_nice = 20
    with pytest.raises(ValueError, match="optimizer_nice"):
        options.validate()
    options.fusion.optimizer_nice = 10
    options.writer_nice = -1
    with pytest.raises(ValueError, match="writer_nice"):
        options.validate()
