// The whole pipeline as a library object on a simulated flight: radiometric compensation of
// automatic-gain-control jumps, bad frames skipped with reasons, and the library API a GIS
// pipeline uses (validated options, poses pushed directly, published generations, the mosaic
// window with its geotransform checked against GDAL, per-frame records).
#include "irmosaic/mosaicker.h"

#include <gdal_priv.h>
#include <gtest/gtest.h>
#include <malloc.h>

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>
#include <thread>

#include "irmosaic/error.h"
#include "irmosaic/evaluator.h"
#include "irmosaic/frame_geometry.h"
#include "irmosaic/orthorectify.h"
#include "irmosaic/simulator.h"
#include "test_data.h"

namespace irmosaic {
namespace {
namespace fs = std::filesystem;

SynthOptions Flight(int frames) {
  SynthOptions options;
  options.ground_path = testing::SamplePath("sample_flight/ground_naip_2019.tif");
  options.seed = 11;
  options.frame_count = frames;
  options.altitude_m = 600;
  options.heading_deg = 80;
  options.frames_per_sweep = 8;
  options.sensor.noise_psnr_db = 35.0;
  return options;
}

// Mean absolute difference between frames i and j over their overlap on the mosaic, each
// frame rendered with its placement and (gain, offset), as a fraction of the value range.
double OverlapDifference(const FlightSimulator& sim, const std::vector<FramePlacement>& placed,
                         const std::vector<cv::Mat>& images, int i, int j, bool compensated,
                         double range) {
  const OrthoImage a = Orthorectify(images[i], sim.camera(), placed[i].mosaic_from_image);
  const OrthoImage b = Orthorectify(images[j], sim.camera(), placed[j].mosaic_from_image);
  const cv::Rect ra(a.origin_px, a.image.size()), rb(b.origin_px, b.image.size());
  const cv::Rect common = ra & rb;
  if (common.area() == 0) return -1.0;
  cv::Mat va, vb;
  a.image(common - a.origin_px)
      .convertTo(va, CV_32F, compensated ? placed[i].gain : 1.0,
                 compensated ? placed[i].offset : 0.0);
  b.image(common - b.origin_px)
      .convertTo(vb, CV_32F, compensated ? placed[j].gain : 1.0,
                 compensated ? placed[j].offset : 0.0);
  cv::Mat both = a.mask(common - a.origin_px) & b.mask(common - b.origin_px);
  cv::erode(both, both, cv::Mat(), cv::Point(-1, -1), 3);
  if (cv::countNonZero(both) < 500) return -1.0;
  // Blur away the sensor noise so the figure measures the radiometric mismatch.
  cv::GaussianBlur(va, va, cv::Size(0, 0), 3.0);
  cv::GaussianBlur(vb, vb, cv::Size(0, 0), 3.0);
  cv::Mat diff;
  cv::absdiff(va, vb, diff);
  return cv::mean(diff, both)[0] / range;
}

TEST(MosaickerTest, GainJumpsAreCompensatedAcrossOverlaps) {
  SynthOptions options = Flight(48);
  options.sensor.agc_gain_jump_fraction = 0.2;  // Gain levels uniform in 1 +- 20 %.
  options.sensor.agc_period_s = 0.12;           // A new level every 3 frames.
  options.sensor.vignetting = false;            // A separate effect (not compensated).
  FlightSimulator sim(options);
  const std::string store =
      (fs::temp_directory_path() / ("irmosaic_gain_" + std::to_string(::getpid()))).string();
  MosaickerOptions mo;
  mo.store_path = store;
  mo.mode = TileStoreOptions::Mode::kOverwrite;
  Mosaicker mosaicker(mo, sim.camera(), sim.MeasuredPos());
  std::vector<cv::Mat> images;
  for (int i = 0; i < sim.frame_count(); ++i) {
    SimFrame f = sim.Render(i);
    images.push_back(f.image);
    ASSERT_TRUE(mosaicker.Push(i, f.time_s, f.image).placed());
  }
  mosaicker.Finish();
  const std::vector<FramePlacement> placed = mosaicker.Placements();
  // The value range of the flight: 1st to 99th percentile of a frame.
  cv::Mat sorted;
  images[0].reshape(1, 1).convertTo(sorted, CV_32F);
  cv::sort(sorted, sorted, cv::SORT_ASCENDING);
  const double range =
      sorted.at<float>(sorted.cols * 99 / 100) - sorted.at<float>(sorted.cols / 100);
  double before = 0.0, after = 0.0;
  int pairs = 0;
  for (int j = 1; j < sim.frame_count(); ++j) {
    if (j % 8 == 0) continue;  // Fly-back: the previous frame is on the other side.
    const double b = OverlapDifference(sim, placed, images, j - 1, j, false, range);
    const double a = OverlapDifference(sim, placed, images, j - 1, j, true, range);
    if (b < 0 || a < 0) continue;
    before += b;
    after += a;
    ++pairs;
  }
  before /= pairs;
  after /= pairs;
  std::printf("overlap difference over %d pairs: before %.2f %%, after %.2f %% of the range\n",
              pairs, 100 * before, 100 * after);
  EXPECT_GT(pairs, 30);
  EXPECT_LT(after, 0.02);
  EXPECT_LT(after, 0.5 * before);
  fs::remove_all(store);
}

// The last, most oblique frame of a sweep deep in the sample flight (frame 48271 of the hour
// `flight_bench` runs): POS predicts its offsets to the previous frame and to the previous
// sweep 87 and 142 px from the truth, beyond the coarse match's first 64 px radius, so both
// pairs fail there and the frame falls back to POS (81 px off; in the 8-bit hour, before the
// limit on joint fits from the coarse translation alone, one pair was accepted in a wrong basin
// and put it 153 px off). Searched again at the wide radius (128 px), it registers.
TEST(MosaickerTest, ASweepEndFrameBeyondTheFirstSearchRadiusRegistersAtTheWideOne) {
  SynthOptions options = SynthOptions::LoadJson(testing::SamplePath("sample_flight/flight.json"));
  constexpr int kFirst = 48240, kFrame = 48271, kLast = 48280;
  options.frame_count = kLast + 1;
  const FlightSimulator sim(options);
  const std::string store =
      (fs::temp_directory_path() / ("irmosaic_wide_" + std::to_string(::getpid()))).string();
  Placements truth;
  truth.origin_lat_deg = sim.frame().origin_lat_deg();
  truth.origin_lon_deg = sim.frame().origin_lon_deg();
  truth.gsd_m = sim.grid().gsd_m;
  truth.image_width = sim.camera().width;
  truth.image_height = sim.camera().height;
  truth.frames.push_back({kFrame, 0.0, sim.TrueMosaicFromImage(kFrame)});
  // Frame kFrame's placement and its error against the truth (truth pixels), and the error of
  // its POS placement.
  auto place = [&](double wide_radius_px, FramePlacement* frame, double* error_px,
                   double* pos_error_px) {
    MosaickerOptions mo;
    mo.store_path = store;
    mo.mode = TileStoreOptions::Mode::kOverwrite;
    mo.ground_height_m = sim.options().ground_height_m;
    mo.wide_search_radius_px = wide_radius_px;
    Mosaicker mosaicker(mo, sim.camera(), sim.MeasuredPos());
    for (int i = kFirst; i <= kLast; ++i) {
      const SimFrame f = sim.Render(i);
      ASSERT_TRUE(mosaicker.Push(i, f.time_s, f.image).placed()) << "frame " << i;
    }
    mosaicker.Finish();
    Placements run, pos;
    run.origin_lat_deg = pos.origin_lat_deg = mosaicker.summary().origin_lat_deg;
    run.origin_lon_deg = pos.origin_lon_deg = mosaicker.summary().origin_lon_deg;
    run.gsd_m = pos.gsd_m = mosaicker.summary().gsd_m;
    for (const FramePlacement& p : mosaicker.Placements()) {
      if (p.index != kFrame) continue;
      *frame = p;
      run.frames.push_back({kFrame, p.time_s, p.mosaic_from_image});
      pos.frames.push_back({kFrame, p.time_s, p.pos_mosaic_from_image});
    }
    const PlacementScore score = Evaluator(truth).ScorePlacements(run, "run");
    const PlacementScore pos_score = Evaluator(truth).ScorePlacements(pos, "pos");
    ASSERT_EQ(score.frames_scored, 1);
    ASSERT_EQ(pos_score.frames_scored, 1);
    *error_px = score.rmse_px.max;
    *pos_error_px = pos_score.rmse_px.max;
  };
  FramePlacement wide, narrow;
  double wide_px = 0.0, narrow_px = 0.0, pos_px = 0.0;
  place(128.0, &wide, &wide_px, &pos_px);
  place(0.0, &narrow, &narrow_px, &pos_px);
  std::printf(
      "frame %d: POS %.1f px; first radius only %.1f px (%s); with the wide try %.2f px "
      "(%zu neighbours)\n",
      kFrame, pos_px, narrow_px, narrow.pos_only ? "POS only" : "registered", wide_px,
      wide.neighbours.size());
  EXPECT_TRUE(narrow.pos_only);
  EXPECT_GT(narrow_px, 40.0);
  EXPECT_GT(pos_px, 40.0);
  // Registered: within the few pixels a sweep's last frame is placed to in this flight (its
  // far field is magnified; 2.8 px here), where POS alone is 81 px off.
  EXPECT_FALSE(wide.pos_only) << wide.note;
  EXPECT_GE(wide.neighbours.size(), 1u);
  EXPECT_LT(wide_px, 8.0);
  fs::remove_all(store);
}

TEST(MosaickerTest, BadFramesAreSkippedWithReasonsAndTheRunGoesOn) {
  FlightSimulator sim(Flight(6));
  const std::string store =
      (fs::temp_directory_path() / ("irmosaic_bad_" + std::to_string(::getpid()))).string();
  MosaickerOptions mo;
  mo.store_path = store;
  mo.mode = TileStoreOptions::Mode::kOverwrite;
  Mosaicker mosaicker(mo, sim.camera(), sim.MeasuredPos());
  const SimFrame f0 = sim.Render(0);
  EXPECT_TRUE(mosaicker.Push(0, f0.time_s, f0.image).placed());
  // Outside the POS time range.
  const PushResult late = mosaicker.Push(1, 1000.0, sim.Render(1).image);
  EXPECT_FALSE(late.placed());
  EXPECT_NE(late.reason.find("frame 1"), std::string::npos) << late.reason;
  EXPECT_NE(late.reason.find("after the last POS record"), std::string::npos) << late.reason;
  // Wrong size, wrong type, empty.
  const PushResult small = mosaicker.Push(2, sim.Render(2).time_s, cv::Mat(100, 100, CV_16U));
  EXPECT_FALSE(small.placed());
  EXPECT_NE(small.reason.find("camera file says 640x512"), std::string::npos) << small.reason;
  EXPECT_FALSE(mosaicker.Push(3, sim.Render(3).time_s, cv::Mat()).placed());
  const SimFrame f3 = sim.Render(3);
  cv::Mat eight;
  f3.image.convertTo(eight, CV_8U, 1.0 / 256);
  const PushResult depth = mosaicker.Push(3, f3.time_s, eight);
  EXPECT_FALSE(depth.placed());
  EXPECT_NE(depth.reason.find("bit depth"), std::string::npos) << depth.reason;
  // The run goes on.
  const SimFrame f4 = sim.Render(4);
  EXPECT_TRUE(mosaicker.Push(4, f4.time_s, f4.image).placed());
  mosaicker.Finish();
  EXPECT_EQ(mosaicker.summary().frames_placed, 2);
  EXPECT_EQ(mosaicker.summary().frames_skipped, 4);
  fs::remove_all(store);
}

std::string TempStore(const std::string& name) {
  return (fs::temp_directory_path() / ("irmosaic_" + name + "_" + std::to_string(::getpid())))
      .string();
}

// The message IsValid gives (empty if valid) and the constructor's InputError text.
std::pair<std::string, std::string> Refusal(const MosaickerOptions& options) {
  std::string error;
  if (options.IsValid(&error)) error.clear();
  std::string thrown;
  try {
    FlightSimulator sim(Flight(2));
    Mosaicker m(options, sim.camera(), sim.MeasuredPos());
  } catch (const InputError& e) {
    thrown = e.what();
  }
  return {error, thrown};
}

TEST(MosaickerApiTest, OptionsAreValidatedWithMessagesNamingTheOption) {
  MosaickerOptions good;
  good.store_path = TempStore("never_opened");
  std::string error;
  EXPECT_TRUE(good.IsValid(&error)) << error;
  struct Case {
    const char* name;
    void (*change)(MosaickerOptions*);
  };
  const Case cases[] = {
      {"store_path", [](MosaickerOptions* o) { o->store_path.clear(); }},
      {"tile_size", [](MosaickerOptions* o) { o->tile_size = 100; }},
      {"tile_size", [](MosaickerOptions* o) { o->tile_size = 0; }},
      {"tile_size", [](MosaickerOptions* o) { o->tile_size = 1 << 20; }},
      {"compression", [](MosaickerOptions* o) { o->compression = "JPEG"; }},
      {"gsd_m", [](MosaickerOptions* o) { o->gsd_m = -1.0; }},
      {"gsd_m", [](MosaickerOptions* o) { o->gsd_m = std::numeric_limits<double>::infinity(); }},
      {"search_radius_px", [](MosaickerOptions* o) { o->search_radius_px = 2.0; }},
      {"wide_search_radius_px", [](MosaickerOptions* o) { o->wide_search_radius_px = 32.0; }},
      {"wide_search_radius_px", [](MosaickerOptions* o) { o->wide_search_radius_px = 2048.0; }},
      {"publish_interval_s", [](MosaickerOptions* o) { o->publish_interval_s = 0.0; }},
      {"publish_interval_s",
       [](MosaickerOptions* o) {
         o->publish_interval_s = std::numeric_limits<double>::infinity();
       }},
      {"heap_trim_interval_frames", [](MosaickerOptions* o) { o->heap_trim_interval_frames = -1; }},
      {"max_cached_tiles", [](MosaickerOptions* o) { o->max_cached_tiles = 0; }},
      {"writer_nice", [](MosaickerOptions* o) { o->writer_nice = 20; }},
      {"optimizer_nice", [](MosaickerOptions* o) { o->fusion.optimizer_nice = -1; }},
      {"max_output_backlog_s", [](MosaickerOptions* o) { o->fusion.max_output_backlog_s = -1; }},
      {"max_range_m", [](MosaickerOptions* o) { o->max_range_m = std::nan(""); }},
      {"pos_position_sigma_m", [](MosaickerOptions* o) { o->pos_position_sigma_m = 0.0; }},
      {"fusion", [](MosaickerOptions* o) { o->fusion.window_frames = -5; }},
      {"origin_lat_deg", [](MosaickerOptions* o) { o->origin_lat_deg = 91.0; }},
      {"origin_lon_deg", [](MosaickerOptions* o) { o->origin_lat_deg = 47.0; }},
  };
  for (const Case& c : cases) {
    MosaickerOptions bad = good;
    c.change(&bad);
    const auto [message, thrown] = Refusal(bad);
    EXPECT_NE(message.find(c.name), std::string::npos) << c.name << ": '" << message << "'";
    EXPECT_NE(thrown.find(c.name), std::string::npos) << c.name << ": '" << thrown << "'";
  }
  EXPECT_FALSE(fs::exists(good.store_path));  // Refused before anything was written.
}

TEST(MosaickerApiTest, AnEmptyPosTrackNeedsTheOriginAndGsd) {
  FlightSimulator sim(Flight(2));
  MosaickerOptions options;
  options.store_path = TempStore("empty_pos");
  try {
    Mosaicker m(options, sim.camera(), PosTrack());
    ADD_FAILURE() << "an empty POS track without origin was accepted";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("origin_lat_deg, origin_lon_deg and gsd_m"),
              std::string::npos)
        << e.what();
  }
  options.origin_lat_deg = 95.0;
  options.origin_lon_deg = 8.0;
  options.gsd_m = 0.3;
  EXPECT_THROW(Mosaicker(options, sim.camera(), PosTrack()), InputError);
}

// Under a sanitizer, its own allocator replaces glibc's, whose figures the test reads. GCC
// says so by __SANITIZE_ADDRESS__ / __SANITIZE_THREAD__, Clang 14 (the sanitize build's
// compiler) only by __has_feature.
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
#define IRMOSAIC_UNDER_SANITIZER 1
#elif defined(__has_feature)
#if __has_feature(address_sanitizer) || __has_feature(thread_sanitizer)
#define IRMOSAIC_UNDER_SANITIZER 1
#endif
#endif
#if defined(__GLIBC__) && !defined(IRMOSAIC_UNDER_SANITIZER)
// MosaickerOptions::tune_heap: once a Mosaicker is made, a 24 MiB buffer (an image-sized one
// is a few MiB; glibc's own threshold starts at 128 KiB) comes from the heap, not a mapping of
// its own, and freeing it leaves the heap as large as it was (no trim on free: the next buffer
// does not fault its pages in again). The tuning is process-wide and stays for the process.
// glibc's figures sum every arena, and other threads (this Mosaicker's, earlier tests' in the
// same process) may return heap memory meanwhile, so each check reads only the figure the step
// under test moves: bytes in use and mapped across the malloc, size and free bytes across the
// free (run alone it passed; after the other tests of this binary, in one process, the arena
// shrank by 12 MiB between the first two readings).
TEST(MosaickerApiTest, TheTunedHeapKeepsLargeBuffersAndDoesNotTrimOnFree) {
  FlightSimulator sim(Flight(2));
  MosaickerOptions options;
  options.store_path = TempStore("tuned_heap");
  ASSERT_TRUE(options.tune_heap);  // The default.
  Mosaicker mosaicker(options, sim.camera(), sim.MeasuredPos());
  constexpr size_t kBytes = 24u << 20;
  const struct mallinfo2 before = mallinfo2();
  char* volatile buffer = static_cast<char*>(std::malloc(kBytes));
  ASSERT_NE(buffer, nullptr);
  std::memset(buffer, 1, kBytes);
  const struct mallinfo2 held = mallinfo2();
  EXPECT_LT(held.hblkhd, before.hblkhd + kBytes / 2) << "the buffer got a mapping of its own";
  EXPECT_GE(held.uordblks, before.uordblks + kBytes / 2) << "the buffer did not come from the heap";
  std::free(buffer);
  const struct mallinfo2 after = mallinfo2();
  EXPECT_GT(after.arena + kBytes / 2, held.arena) << "the heap was trimmed on free";
  EXPECT_GE(after.fordblks, held.fordblks + kBytes / 2) << "the freed buffer left the heap";
}
#endif

// Poses given with each frame (a live POS stream, no track) place frames as the track does.
TEST(MosaickerApiTest, PosesPushedDirectlyPlaceFramesAsTheTrackDoes) {
  FlightSimulator sim(Flight(5));
  MosaickerOptions with_track;
  with_track.store_path = TempStore("track");
  with_track.mode = TileStoreOptions::Mode::kOverwrite;
  Mosaicker tracked(with_track, sim.camera(), sim.MeasuredPos());

  MosaickerOptions with_poses = with_track;
  with_poses.store_path = TempStore("poses");
  with_poses.origin_lat_deg = tracked.georeference().origin_lat_deg;
  with_poses.origin_lon_deg = tracked.georeference().origin_lon_deg;
  with_poses.gsd_m = tracked.georeference().gsd_m;
  Mosaicker posed(with_poses, sim.camera(), PosTrack());
  EXPECT_EQ(posed.georeference().crs_wkt, tracked.georeference().crs_wkt);

  for (int i = 0; i < 5; ++i) {
    const SimFrame f = sim.Render(i);
    const PushResult a = tracked.Push(i, f.time_s, f.image);
    const PushResult b = posed.Push(i, f.time_s, PoseFromRecord(f.measured_pos), f.image);
    ASSERT_TRUE(a.placed()) << a.reason;
    ASSERT_TRUE(b.placed()) << b.reason;
    // Same POS prediction (the track interpolates at a sample time): same corners to 1e-3 px.
    for (const Eigen::Vector2d& corner : {Eigen::Vector2d(0, 0), Eigen::Vector2d(639, 511)}) {
      const Eigen::Vector2d pa = ApplyHomography(a.placement.pos_mosaic_from_image, corner);
      const Eigen::Vector2d pb = ApplyHomography(b.placement.pos_mosaic_from_image, corner);
      EXPECT_LT((pa - pb).norm(), 1e-3) << "frame " << i;
    }
  }
  // A pose that is not finite is a skipped frame with a reason, not a crash.
  Pose broken = PoseFromRecord(sim.Render(0).measured_pos);
  broken.lat_deg = std::nan("");
  const PushResult skipped = posed.Push(9, 0.0, broken, sim.Render(0).image);
  EXPECT_FALSE(skipped.placed());
  EXPECT_NE(skipped.reason.find("pose is not finite"), std::string::npos) << skipped.reason;
  tracked.Finish();
  posed.Finish();
  EXPECT_EQ(posed.summary().frames_placed, 5);
  EXPECT_EQ(posed.summary().frames_skipped, 1);
  fs::remove_all(with_track.store_path);
  fs::remove_all(with_poses.store_path);
}

// The store's planned extent (what the GDAL plug-in serves from the first generation, so QGIS
// shows the flight fill in without a reload) is foreseen from the POS track: it holds every
// frame's placed footprint, and no more than the documented margin beyond them.
TEST(MosaickerApiTest, ThePlannedExtentHoldsEveryFrameTheTrackForesees) {
  FlightSimulator sim(Flight(6));
  MosaickerOptions options;
  options.store_path = TempStore("planned");
  options.mode = TileStoreOptions::Mode::kOverwrite;
  Mosaicker m(options, sim.camera(), sim.MeasuredPos());
  MosaickerOptions unplanned = options;
  unplanned.store_path = TempStore("unplanned");
  unplanned.planned_extent = false;
  Mosaicker u(unplanned, sim.camera(), sim.MeasuredPos());
  for (int i = 0; i < 6; ++i) {
    const SimFrame f = sim.Render(i);
    ASSERT_TRUE(m.Push(i, f.time_s, f.image).placed());
    ASSERT_TRUE(u.Push(i, f.time_s, f.image).placed());
  }
  m.Finish();
  u.Finish();
  const auto manifest_of = [](const std::string& store) {
    std::ifstream in(fs::path(store) / "manifest.json");
    return nlohmann::json::parse(in);
  };
  const nlohmann::json planned = manifest_of(options.store_path)["planned_bounds_px"];
  ASSERT_TRUE(planned.is_object()) << planned;
  EXPECT_TRUE(manifest_of(unplanned.store_path)["planned_bounds_px"].is_null());
  // The placed footprints' bounding box, mosaic pixels.
  const double gsd = m.georeference().gsd_m;
  double x0 = HUGE_VAL, y0 = HUGE_VAL, x1 = -HUGE_VAL, y1 = -HUGE_VAL;
  for (const FrameRecord& record : m.FrameRecords()) {
    for (const Eigen::Vector2d& corner : record.footprint_m) {
      x0 = std::min(x0, corner.x() / gsd);
      x1 = std::max(x1, corner.x() / gsd);
      y0 = std::min(y0, -corner.y() / gsd);
      y1 = std::max(y1, -corner.y() / gsd);
    }
  }
  ASSERT_EQ(m.FrameRecords().size(), 6u);
  EXPECT_LE(planned["col_min"].get<double>(), x0);
  EXPECT_LE(planned["row_min"].get<double>(), y0);
  EXPECT_GE(planned["col_max"].get<double>(), x1);
  EXPECT_GE(planned["row_max"].get<double>(), y1);
  // Margin: 3 POS sigmas and a tile, plus what the POS error itself moves a footprint (2 m and
  // 0.3 deg at this range: well under 60 px).
  const double margin = 3.0 * options.pos_position_sigma_m / gsd + options.tile_size + 60.0;
  EXPECT_GE(planned["col_min"].get<double>(), x0 - margin);
  EXPECT_GE(planned["row_min"].get<double>(), y0 - margin);
  EXPECT_LE(planned["col_max"].get<double>(), x1 + margin);
  EXPECT_LE(planned["row_max"].get<double>(), y1 + margin);
  fs::remove_all(options.store_path);
  fs::remove_all(unplanned.store_path);
}

// Reads band 1 and the alpha band of a raster whole through GDAL.
struct GdalRaster {
  std::array<double, 6> geotransform = {};
  cv::Mat values, alpha;
};
GdalRaster ReadWithGdal(const std::string& path, int cv_type) {
  GDALAllRegister();
  GdalRaster out;
  std::unique_ptr<GDALDataset> ds(GDALDataset::FromHandle(GDALOpen(path.c_str(), GA_ReadOnly)));
  if (!ds) return out;
  ds->GetGeoTransform(out.geotransform.data());
  const int w = ds->GetRasterXSize(), h = ds->GetRasterYSize();
  out.values = cv::Mat(h, w, cv_type);
  out.alpha = cv::Mat(h, w, cv_type);
  const GDALDataType type = cv_type == CV_8U    ? GDT_Byte
                            : cv_type == CV_16U ? GDT_UInt16
                                                : GDT_Float32;
  if (ds->GetRasterBand(1)->RasterIO(GF_Read, 0, 0, w, h, out.values.data, w, h, type, 0, 0) !=
          CE_None ||
      ds->GetRasterBand(2)->RasterIO(GF_Read, 0, 0, w, h, out.alpha.data, w, h, type, 0, 0) !=
          CE_None) {
    return GdalRaster();
  }
  return out;
}

// Finish() publishes the frames placed since the last publish before its final solve (which
// takes seconds on a long window), so the newest frames do not wait for it: OnPublished hears
// of a generation holding the last frame while no solve has refined any frame yet.
TEST(MosaickerApiTest, FinishPublishesTheLastFramesBeforeTheFinalSolve) {
  FlightSimulator sim(Flight(10));
  MosaickerOptions options;
  options.store_path = TempStore("finish_order");
  options.mode = TileStoreOptions::Mode::kOverwrite;
  options.publish_interval_s = 1e6;          // No publish while pushing: all wait for Finish.
  options.fusion.solve_every_frames = 1000;  // No background solve: only Finish's.
  std::vector<std::pair<int64_t, double>> published;  // (index, latency) per frame.
  options.on_frame_published = [&](int64_t index, double latency_s) {
    published.push_back({index, latency_s});
  };
  std::mutex reports_mu;  // The store's reports come on its writer thread.
  std::vector<PublishReport> reports;
  options.on_publish = [&](const PublishReport& r) {
    std::lock_guard<std::mutex> lock(reports_mu);
    reports.push_back(r);
  };
  const auto start = std::chrono::steady_clock::now();
  Mosaicker m(options, sim.camera(), sim.MeasuredPos());
  struct Seen {
    int64_t generation = 0, covered = -1;
    int optimized_frames = 0;
  };
  // Pixels the published mosaic covers, read through GDAL.
  auto covered_on_disk = [&] {
    GDALDatasetH ds = GDALOpen((fs::path(options.store_path) / "mosaic.vrt").c_str(), GA_ReadOnly);
    if (ds == nullptr) return int64_t{-1};
    GDALRasterBandH alpha = GDALGetRasterBand(ds, 2);
    const int w = GDALGetRasterXSize(ds), h = GDALGetRasterYSize(ds);
    cv::Mat a(h, w, CV_8U);
    const bool ok =
        GDALRasterIO(alpha, GF_Read, 0, 0, w, h, a.ptr(), w, h, GDT_Byte, 0, 0) == CE_None;
    GDALClose(ds);
    return ok ? int64_t{cv::countNonZero(a)} : int64_t{-1};
  };
  std::vector<Seen> seen;
  m.OnPublished([&](int64_t generation) {
    Seen s;
    s.generation = generation;
    s.covered = covered_on_disk();
    for (const FramePlacement& p : m.Placements()) s.optimized_frames += p.optimized_times > 0;
    seen.push_back(s);
  });
  for (int i = 0; i < 10; ++i) {
    const SimFrame f = sim.Render(i);
    ASSERT_TRUE(m.Push(i, f.time_s, f.image).placed());
  }
  EXPECT_TRUE(seen.empty());
  m.Finish();
  ASSERT_GE(seen.size(), 2u);
  const int64_t final_covered = covered_on_disk();
  ASSERT_GT(final_covered, 0);
  // Before the final solve: the frames on disk (their footprints cover what the final mosaic
  // does, up to the final solve's sub-pixel to few-pixel moves at the edges), none refined.
  EXPECT_GE(seen.front().covered, final_covered * 97 / 100);
  EXPECT_EQ(seen.front().optimized_frames, 0);
  // After it: every frame refined, in a later generation.
  EXPECT_GT(seen.back().generation, seen.front().generation);
  EXPECT_EQ(seen.back().optimized_frames, 10);
  EXPECT_EQ(m.summary().frames_placed, 10);
  // Each frame's publish latency reported once, in push order, the summary's quantiles made of
  // the same figures; none longer than the whole test has run.
  const double elapsed_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  ASSERT_EQ(published.size(), 10u);
  double max_latency_s = 0.0;
  for (int i = 0; i < 10; ++i) {
    EXPECT_EQ(published[static_cast<size_t>(i)].first, i);
    EXPECT_GE(published[static_cast<size_t>(i)].second, 0.0);
    EXPECT_LE(published[static_cast<size_t>(i)].second, elapsed_s);
    max_latency_s = std::max(max_latency_s, published[static_cast<size_t>(i)].second);
  }
  EXPECT_EQ(max_latency_s, m.summary().publish_latency_max_s);
  // The store's reports (passed through to it): one per publish, generations rising, the first
  // one (Finish's, before the final solve) writing the frames' tiles; every frame's latency ends
  // at its publish's finish, no later than the first report's.
  {
    std::lock_guard<std::mutex> lock(reports_mu);
    ASSERT_GE(reports.size(), 2u);
    EXPECT_EQ(reports.front().generation, seen.front().generation);
    EXPECT_GT(reports.front().level0_tiles, 0);
    for (size_t k = 1; k < reports.size(); ++k) {
      EXPECT_GT(reports[k].generation, reports[k - 1].generation);
    }
    EXPECT_EQ(reports.back().generation, seen.back().generation);
    const double first_finished_s =
        std::chrono::duration<double>(reports.front().finished - start).count();
    EXPECT_LE(max_latency_s, first_finished_s);
  }
  fs::remove_all(options.store_path);
}

TEST(MosaickerApiTest, GenerationsWindowAndRecordsAgreeWithWhatGdalReads) {
  FlightSimulator sim(Flight(6));
  MosaickerOptions options;
  options.store_path = TempStore("api");
  options.mode = TileStoreOptions::Mode::kOverwrite;
  options.publish_interval_s = 1e-3;
  Mosaicker m(options, sim.camera(), sim.MeasuredPos());
  // Before any frame: nothing to read, nothing published.
  EXPECT_TRUE(m.bounds_px().empty());
  EXPECT_TRUE(m.FrameRecords().empty());
  EXPECT_EQ(m.published_generation(), 0);
  EXPECT_THROW(m.ReadWindow(cv::Rect(0, 0, 10, 10)), InputError);

  std::vector<int64_t> generations;
  m.OnPublished([&](int64_t generation) { generations.push_back(generation); });

  // A reader thread polls the live mosaic while frames are pushed: coverage of a fixed window
  // only grows (painting never uncovers a pixel).
  std::atomic<bool> done{false};
  std::atomic<int> reads{0}, shrinks{0}, errors{0};
  std::thread reader([&] {
    cv::Rect window;
    int last_covered = 0;
    while (!done.load()) {
      try {
        if (window.empty()) window = m.bounds_px();
        if (!window.empty()) {
          const MosaicWindow w = m.ReadWindow(window);
          const int covered = cv::countNonZero(w.coverage);
          if (covered < last_covered) ++shrinks;
          last_covered = covered;
          ++reads;
        }
        (void)m.summary();
        (void)m.FrameRecords();
        (void)m.published_generation();
      } catch (const std::exception&) {
        ++errors;
      }
      std::this_thread::yield();
    }
  });
  for (int i = 0; i < 6; ++i) {
    const SimFrame f = sim.Render(i);
    ASSERT_TRUE(m.Push(i, f.time_s, f.image).placed());
  }
  m.RequestPublish();
  m.WaitPublished(m.published_generation() + 1);
  EXPECT_GE(m.published_generation(), 1);
  m.Finish();
  done = true;
  reader.join();
  EXPECT_EQ(errors.load(), 0);
  EXPECT_EQ(shrinks.load(), 0);

  // The callback saw increasing generations, the last one being the final publish.
  ASSERT_FALSE(generations.empty());
  for (size_t k = 1; k < generations.size(); ++k) EXPECT_GT(generations[k], generations[k - 1]);
  EXPECT_EQ(generations.back(), m.published_generation());
  EXPECT_EQ(generations.back(), m.summary().generations_published);

  // The window with its geotransform matches mosaic.vrt as GDAL reads it, pixel for pixel.
  const cv::Rect bounds = m.bounds_px();
  ASSERT_FALSE(bounds.empty());
  const cv::Rect inner(bounds.x + 37, bounds.y + 53, bounds.width / 2, bounds.height / 2);
  const MosaicWindow w = m.ReadWindow(inner);
  EXPECT_EQ(w.image.type(), CV_16U);
  EXPECT_EQ(w.image.size(), inner.size());
  EXPECT_EQ(w.crs_wkt, m.georeference().crs_wkt);
  const double gsd = m.georeference().gsd_m;
  EXPECT_DOUBLE_EQ(w.geotransform[1], gsd);
  EXPECT_DOUBLE_EQ(w.geotransform[5], -gsd);
  const GdalRaster vrt = ReadWithGdal(options.store_path + "/mosaic.vrt", CV_16U);
  ASSERT_FALSE(vrt.values.empty());
  EXPECT_DOUBLE_EQ(vrt.geotransform[1], gsd);
  // Where the window's top-left corner falls in the VRT: a whole pixel offset.
  const double dx = (w.geotransform[0] - vrt.geotransform[0]) / gsd;
  const double dy = (w.geotransform[3] - vrt.geotransform[3]) / -gsd;
  EXPECT_NEAR(dx, std::round(dx), 1e-6);
  EXPECT_NEAR(dy, std::round(dy), 1e-6);
  const cv::Rect in_vrt(static_cast<int>(std::lround(dx)), static_cast<int>(std::lround(dy)),
                        inner.width, inner.height);
  ASSERT_EQ(in_vrt & cv::Rect(0, 0, vrt.values.cols, vrt.values.rows), in_vrt);
  const int covered = cv::countNonZero(w.coverage);
  EXPECT_GT(covered, inner.area() / 4);
  cv::Mat differ;
  cv::compare(w.image, vrt.values(in_vrt), differ, cv::CMP_NE);
  EXPECT_EQ(cv::countNonZero(differ & w.coverage), 0);
  cv::Mat alpha_set = vrt.alpha(in_vrt) > 0;
  cv::Mat coverage_differs;
  cv::compare(alpha_set, w.coverage, coverage_differs, cv::CMP_NE);
  EXPECT_EQ(cv::countNonZero(coverage_differs), 0);

  // One record per placed frame; its footprint is the placement's image corners on the plane,
  // as of the last render (a frame is re-rendered when it moved more than
  // rerender_threshold_px, so the record lags the placement by less than that).
  const std::vector<FrameRecord> records = m.FrameRecords();
  const std::vector<FramePlacement> placements = m.Placements();
  ASSERT_EQ(records.size(), 6u);
  ASSERT_EQ(placements.size(), 6u);
  const std::array<Eigen::Vector2d, 4> corners = {
      Eigen::Vector2d(-0.5, -0.5), Eigen::Vector2d(639.5, -0.5), Eigen::Vector2d(639.5, 511.5),
      Eigen::Vector2d(-0.5, 511.5)};
  for (size_t k = 0; k < records.size(); ++k) {
    EXPECT_EQ(records[k].index, placements[k].index);
    EXPECT_EQ(records[k].pos_only, placements[k].pos_only);
    for (int c = 0; c < 4; ++c) {
      const Eigen::Vector2d px = ApplyHomography(placements[k].mosaic_from_image, corners[c]);
      const Eigen::Vector2d plane(px.x() * gsd, -px.y() * gsd);
      EXPECT_LT((records[k].footprint_m[c] - plane).norm() / gsd,
                options.fusion.rerender_threshold_px + 0.01)
          << "frame " << k << " corner " << c;
    }
  }
  fs::remove_all(options.store_path);
}

// The store records every published placement for --resume (docs/store.md, "Resume record"): a
// resumed Mosaicker holds every frame of the killed run before it pushes anything, each exactly
// where the store put it, and asks back only for the frames still in the optimizer's window.
// A record whose placement is not finite (NaN is written as null) is refused, naming the store
// and the frame, instead of placing frames at NaN.
// Memory flat over a flight: with a store, the placements of frames that left the window are
// read back from the frozen frames' file, and the frame records from frames.gpkg, instead of
// held for the whole flight; Placements() and FrameRecords() return the same as with
// everything held (every field of every placement, exactly), while the fusion holds no more
// than its windows and the store no more than the records not yet written.
TEST(MosaickerApiTest, FrozenPlacementsAndRecordsLeaveMemoryAndReadBackExactly) {
  constexpr int kFrames = 28;  // 3.5 sweeps, 7 windows.
  FlightSimulator sim(Flight(kFrames));
  auto run = [&sim](bool keep, const std::string& name) {
    MosaickerOptions options;
    options.store_path = TempStore(name);
    options.mode = TileStoreOptions::Mode::kOverwrite;
    options.fusion.window_frames = 4;
    options.fusion.optimize = false;  // Deterministic: both runs place alike.
    options.keep_placements_in_memory = keep;
    options.overview_interval_s = 0.0;  // frames.gpkg with every publish.
    auto m = std::make_unique<Mosaicker>(options, sim.camera(), sim.MeasuredPos());
    int64_t most_held = 0;
    size_t most_records = 0;
    for (int i = 0; i < kFrames; ++i) {
      const SimFrame f = sim.Render(i);
      EXPECT_TRUE(m->Push(i, f.time_s, f.image).placed()) << i;
      if (i % 2 == 0) continue;
      m->RequestPublish();  // With the resume record (frozen frames to their file), then wait.
      m->WaitPublished(m->store()->RequestPublish());
      most_held = std::max(most_held, m->summary().fusion.placements_held);
      most_records = std::max(most_records, m->store()->stats().frame_records_held);
    }
    m->Finish();
    return std::make_tuple(m->Placements(), m->FrameRecords(), most_held, most_records);
  };
  const auto [kept, kept_records, kept_held, kept_most_records] = run(true, "kept");
  const auto [read, read_records, read_held, read_most_records] = run(false, "released");
  std::printf("placements held at most: %lld of %d kept, %lld released; records held at most %zu\n",
              static_cast<long long>(kept_held), kFrames, static_cast<long long>(read_held),
              read_most_records);
  EXPECT_EQ(kept_held, kFrames);
  // The window (4 frames, held up to 2 windows) and the bases of its pairs (a sweep, 8 frames,
  // back), with the frames placed since the last publish among them: a bound that does not
  // grow with the flight.
  EXPECT_LE(read_held, 16);
  EXPECT_LE(read_most_records, 2u);  // Written with each publish, so at most the newest.
  ASSERT_EQ(read.size(), kept.size());
  ASSERT_EQ(read.size(), static_cast<size_t>(kFrames));
  for (size_t k = 0; k < kept.size(); ++k) {
    const FramePlacement& a = kept[k];
    const FramePlacement& b = read[k];
    EXPECT_EQ(a.index, b.index);
    EXPECT_EQ(a.time_s, b.time_s) << k;
    EXPECT_EQ(a.mosaic_from_image, b.mosaic_from_image) << k;
    EXPECT_EQ(a.pos_mosaic_from_image, b.pos_mosaic_from_image) << k;
    EXPECT_EQ(a.pos_only, b.pos_only) << k;
    EXPECT_EQ(a.neighbours, b.neighbours) << k;
    EXPECT_EQ(a.inliers, b.inliers) << k;
    EXPECT_EQ(a.residual_px, b.residual_px) << k;
    EXPECT_EQ(a.gain, b.gain) << k;
    EXPECT_EQ(a.offset, b.offset) << k;
    EXPECT_EQ(a.optimized_times, b.optimized_times) << k;
    EXPECT_EQ(a.note, b.note) << k;
  }
  ASSERT_EQ(read_records.size(), kept_records.size());
  ASSERT_EQ(read_records.size(), static_cast<size_t>(kFrames));
  for (size_t k = 0; k < read_records.size(); ++k) {
    EXPECT_EQ(read_records[k].index, static_cast<int64_t>(k));
    EXPECT_EQ(read_records[k].time_s, kept_records[k].time_s);
    EXPECT_EQ(read_records[k].status, kept_records[k].status);
    for (int c = 0; c < 4; ++c) {
      EXPECT_LT((read_records[k].footprint_m[c] - kept_records[k].footprint_m[c]).norm(), 1e-6);
    }
  }
  fs::remove_all(TempStore("kept"));
  fs::remove_all(TempStore("released"));
}

TEST(MosaickerApiTest, AResumedStoreHoldsEveryRecordedPlacementAndRefusesADamagedOne) {
  FlightSimulator sim(Flight(24));
  MosaickerOptions options;
  options.store_path = TempStore("record");
  options.mode = TileStoreOptions::Mode::kOverwrite;
  options.fusion.window_frames = 4;
  std::vector<FramePlacement> written;
  {
    Mosaicker m(options, sim.camera(), sim.MeasuredPos());
    for (int i = 0; i < sim.frame_count(); ++i) {
      const SimFrame f = sim.Render(i);
      ASSERT_TRUE(m.Push(i, f.time_s, f.image).placed()) << i;
    }
    m.Finish();
    written = m.Placements();
  }
  ASSERT_EQ(written.size(), 24u);
  options.mode = TileStoreOptions::Mode::kResume;
  {
    Mosaicker m(options, sim.camera(), sim.MeasuredPos());
    EXPECT_EQ(m.resumed_last_index(), 23);
    EXPECT_TRUE(m.resume_warning().empty()) << m.resume_warning();
    // Held at the end: the last 2 windows (frames 16-23) and the bases of their pairs, which
    // reach back one sweep (8 frames) at most; the frames before are not pushed again.
    std::printf("resume replays frames %lld-23\n", static_cast<long long>(m.resume_replay_from()));
    EXPECT_GE(m.resume_replay_from(), 8);
    EXPECT_LE(m.resume_replay_from(), 16);
    const std::vector<FramePlacement> resumed = m.Placements();
    ASSERT_EQ(resumed.size(), written.size());
    double worst_px = 0.0;
    for (size_t k = 0; k < written.size(); ++k) {
      EXPECT_EQ(resumed[k].index, written[k].index);
      for (const Eigen::Vector2d& corner : {Eigen::Vector2d(0, 0), Eigen::Vector2d(639, 511)}) {
        worst_px = std::max(worst_px, (ApplyHomography(resumed[k].mosaic_from_image, corner) -
                                       ApplyHomography(written[k].mosaic_from_image, corner))
                                          .norm());
      }
    }
    std::printf("recorded placements read back: %zu frames, worst corner %.3g px\n", resumed.size(),
                worst_px);
    EXPECT_LT(worst_px, 1e-9);  // Read back exactly (shortest round-trip text).
    EXPECT_EQ(m.summary().frames_placed, 24);
    // The held frames pushed again (the replay) and a last solve: the finished run's solution
    // again, within the 0.5 px (the solve restarts from it, with its pair weights).
    for (int64_t i = m.resume_replay_from(); i < sim.frame_count(); ++i) {
      const SimFrame f = sim.Render(static_cast<int>(i));
      ASSERT_TRUE(m.Push(i, f.time_s, f.image).placed()) << i;
    }
    m.Finish();
    const std::vector<FramePlacement> again = m.Placements();
    ASSERT_EQ(again.size(), written.size());
    double moved_px = 0.0;
    for (size_t k = 0; k < written.size(); ++k) {
      for (const Eigen::Vector2d& corner : {Eigen::Vector2d(0, 0), Eigen::Vector2d(639, 511)}) {
        moved_px = std::max(moved_px, (ApplyHomography(again[k].mosaic_from_image, corner) -
                                       ApplyHomography(written[k].mosaic_from_image, corner))
                                          .norm());
      }
    }
    std::printf("replayed and solved again: worst corner moved %.3g px\n", moved_px);
    EXPECT_LT(moved_px, 0.5);
  }
  // Frames that left the window are in resume_frames.jsonl (one line each, push order), the
  // rest in the manifest. Either place refuses a placement that is not finite.
  const std::string manifest = options.store_path + "/manifest.json";
  const std::string log = options.store_path + "/resume_frames.jsonl";
  nlohmann::json doc;
  {
    std::ifstream in(manifest);
    doc = nlohmann::json::parse(in);
  }
  const nlohmann::json& record = doc["application"]["fusion"];
  const size_t frozen = record["frozen"]["frames"].get<size_t>();
  std::printf("record: %zu frames in resume_frames.jsonl, %zu in the manifest\n", frozen,
              record["frames"].size());
  ASSERT_GT(frozen, 5u);
  ASSERT_EQ(frozen + record["frames"].size(), 24u);
  std::vector<std::string> lines;
  {
    std::ifstream in(log);
    for (std::string line; std::getline(in, line);) lines.push_back(line);
  }
  ASSERT_EQ(lines.size(), frozen);
  auto refusal = [&]() -> std::string {
    try {
      Mosaicker m(options, sim.camera(), sim.MeasuredPos());
    } catch (const InputError& e) {
      return e.what();
    }
    return "accepted";
  };
  nlohmann::json line5 = nlohmann::json::parse(lines[5]);
  ASSERT_EQ(line5["index"], 5);
  line5["h"][2] = nullptr;  // What a NaN is written as; padded to the line's length.
  std::string damaged = line5.dump();
  ASSERT_LE(damaged.size(), lines[5].size());
  damaged.resize(lines[5].size(), ' ');
  {
    std::ofstream out(log);
    for (size_t k = 0; k < lines.size(); ++k) out << (k == 5 ? damaged : lines[k]) << "\n";
  }
  std::string message = refusal();
  EXPECT_NE(message.find(log + ":6"), std::string::npos) << message;
  EXPECT_NE(message.find("frame 5's stored placement is not finite"), std::string::npos) << message;
  EXPECT_NE(message.find("--overwrite"), std::string::npos) << message;
  {
    std::ofstream out(log);
    for (const std::string& line : lines) out << line << "\n";
  }
  const int64_t moving = doc["application"]["fusion"]["frames"][0]["index"].get<int64_t>();
  doc["application"]["fusion"]["frames"][0]["h"][4] = nullptr;
  std::ofstream(manifest) << doc.dump();
  message = refusal();
  EXPECT_NE(message.find(manifest), std::string::npos) << message;
  EXPECT_NE(message.find("frame " + std::to_string(moving) + "'s stored placement is not finite"),
            std::string::npos)
      << message;
  fs::remove_all(options.store_path);
}

// A frozen frames' file that cannot be written (here a folder in its place; a full disk in the
// field) loses nothing: those frames stay in the manifest's record until an append succeeds,
// and a resume reads them all back exactly.
TEST(MosaickerApiTest, AResumeRecordTheFrozenFileCannotTakeStaysWholeInTheManifest) {
  FlightSimulator sim(Flight(12));
  MosaickerOptions options;
  options.store_path = TempStore("record_full");
  options.mode = TileStoreOptions::Mode::kOverwrite;
  options.fusion.window_frames = 2;
  std::vector<FramePlacement> written;
  {
    Mosaicker m(options, sim.camera(), sim.MeasuredPos());
    for (int i = 0; i < sim.frame_count(); ++i) {
      const SimFrame f = sim.Render(i);
      ASSERT_TRUE(m.Push(i, f.time_s, f.image).placed()) << i;
      if (i == 0) fs::create_directory(options.store_path + "/resume_frames.jsonl");
    }
    m.Finish();
    written = m.Placements();
  }
  nlohmann::json doc;
  {
    std::ifstream in(options.store_path + "/manifest.json");
    doc = nlohmann::json::parse(in);
  }
  const nlohmann::json& record = doc["application"]["fusion"];
  EXPECT_EQ(record["frozen"]["frames"], 0);
  EXPECT_EQ(record["frames"].size(), 12u);
  options.mode = TileStoreOptions::Mode::kResume;
  Mosaicker m(options, sim.camera(), sim.MeasuredPos());
  const std::vector<FramePlacement> resumed = m.Placements();
  ASSERT_EQ(resumed.size(), written.size());
  double worst_px = 0.0;
  for (size_t k = 0; k < written.size(); ++k) {
    const Eigen::Vector2d corner(639, 511);
    worst_px = std::max(worst_px, (ApplyHomography(resumed[k].mosaic_from_image, corner) -
                                   ApplyHomography(written[k].mosaic_from_image, corner))
                                      .norm());
  }
  std::printf("record kept in the manifest: %zu frames read back, worst corner %.3g px\n",
              resumed.size(), worst_px);
  EXPECT_LT(worst_px, 1e-9);
  fs::remove_all(options.store_path);
}

}  // namespace
}  // namespace irmosaic
