#include "irmosaic/mosaicker.h"

#if defined(__GLIBC__)
#include <malloc.h>
#endif

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <deque>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "irmosaic/error.h"
#include "irmosaic/frame_geometry.h"
#include "irmosaic/local_frame.h"
#include "irmosaic/orthorectify.h"
#include "irmosaic/registration.h"
#include "mat_pool.h"

namespace irmosaic {
namespace {

using Clock = std::chrono::steady_clock;

double RoundSignificant(double value, int digits) {
  if (!(value > 0.0)) return value;
  const double scale = std::pow(10.0, digits - 1 - std::floor(std::log10(value)));
  return std::round(value * scale) / scale;
}

PixelType PixelTypeOf(const cv::Mat& image) {
  switch (image.depth()) {
    case CV_8U:
      return PixelType::kByte;
    case CV_16U:
      return PixelType::kUInt16;
    default:
      return PixelType::kFloat32;
  }
}

// Version of the resume record (application state "fusion"); a newer one is refused.
constexpr int kResumeRecordVersion = 1;
// The store file that holds the record of the frames that left the fusion's window (they never
// change again): one JSON line per frame, in push order, appended before the publish whose
// manifest counts them, so the manifest carries only the frames that can still move.
constexpr const char* kFrozenRecordFile = "resume_frames.jsonl";

// One frame of the resume record. Numbers are written so that they read back exactly
// (nlohmann::json writes the shortest text that round-trips a double).
std::vector<double> RowMajor(const Eigen::Matrix3d& m) {
  std::vector<double> terms(9);
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) terms[3 * r + c] = m(r, c);
  return terms;
}

nlohmann::json PlacementRecord(const FramePlacement& p) {
  nlohmann::json record = {{"index", p.index},
                           {"time_s", p.time_s},
                           {"h", RowMajor(p.mosaic_from_image)},
                           {"pos_h", RowMajor(p.pos_mosaic_from_image)},
                           {"pos_only", p.pos_only},
                           {"inliers", p.inliers},
                           {"residual_px", p.residual_px},
                           {"gain", p.gain},
                           {"offset", p.offset},
                           {"optimized", p.optimized_times},
                           {"neighbours", p.neighbours}};
  if (!p.note.empty()) record["note"] = p.note;
  return record;
}

// A damaged resume record is refused, never used: frames must not be placed at NaN.
[[noreturn]] void RefuseRecord(const SourceLocation& where, const std::string& problem) {
  throw InputError(where, problem,
                   "the store's resume record is damaged: start again with --overwrite (the "
                   "published tiles stay readable as they are)");
}

int64_t RecordInteger(const nlohmann::json& j, const char* key, SourceLocation where) {
  where.field += key;
  if (!j.is_object() || !j.contains(key) || !j[key].is_number_integer()) {
    RefuseRecord(where, std::string(key) + " is missing or not an integer");
  }
  return j[key].get<int64_t>();
}

double RecordFinite(const nlohmann::json& j, const char* key, SourceLocation where,
                    const std::string& what) {
  where.field += key;
  if (!j.contains(key) || !j[key].is_number() || !std::isfinite(j[key].get<double>())) {
    RefuseRecord(where, what + " is not a finite number");
  }
  return j[key].get<double>();
}

// The 3 x 3 matrix stored under `key` (9 finite numbers, row by row) of a frame's record.
Eigen::Matrix3d RecordMatrix(const nlohmann::json& f, const char* key, SourceLocation at,
                             const std::string& what) {
  at.field += key;
  if (!f.contains(key) || !f[key].is_array() || f[key].size() != 9) {
    RefuseRecord(at, what + " is not 9 numbers");
  }
  Eigen::Matrix3d m;
  for (int i = 0; i < 9; ++i) {
    const nlohmann::json& v = f[key][static_cast<size_t>(i)];
    if (!v.is_number() || !std::isfinite(v.get<double>())) {
      RefuseRecord(at, what + " is not finite");
    }
    m(i / 3, i % 3) = v.get<double>();
  }
  return m;
}

// One frame of the record; `where` names its place (manifest field or log line).
FramePlacement ParsePlacementRecord(const nlohmann::json& f, const SourceLocation& where) {
  if (!f.is_object()) RefuseRecord(where, "a frame of the resume record is not a JSON object");
  FramePlacement p;
  p.index = RecordInteger(f, "index", where);
  const std::string frame = "frame " + std::to_string(p.index) + "'s ";
  SourceLocation at = where;
  at.field += "h";
  p.time_s = RecordFinite(f, "time_s", where, frame + "time");
  p.mosaic_from_image = RecordMatrix(f, "h", where, frame + "stored placement");
  if (std::abs(p.mosaic_from_image.determinant()) < 1e-12) {
    RefuseRecord(at, frame + "stored placement is singular");
  }
  // The POS placement (recorded since 2026-12-05; before, the placement stands for it).
  p.pos_mosaic_from_image = f.contains("pos_h")
                                ? RecordMatrix(f, "pos_h", where, frame + "POS placement")
                                : p.mosaic_from_image;
  if (f.contains("note")) {
    at.field = where.field + "note";
    if (!f["note"].is_string()) RefuseRecord(at, frame + "note is not text");
    p.note = f["note"].get<std::string>();
  }
  at.field = where.field + "pos_only";
  if (!f.contains("pos_only") || !f["pos_only"].is_boolean()) {
    RefuseRecord(at, frame + "pos_only is missing or not true/false");
  }
  p.pos_only = f["pos_only"].get<bool>();
  p.inliers = static_cast<int>(RecordInteger(f, "inliers", where));
  p.residual_px = RecordFinite(f, "residual_px", where, frame + "residual");
  p.gain = RecordFinite(f, "gain", where, frame + "gain");
  p.offset = RecordFinite(f, "offset", where, frame + "offset");
  p.optimized_times = static_cast<int>(RecordInteger(f, "optimized", where));
  at.field = where.field + "neighbours";
  if (f.contains("neighbours")) {
    if (!f["neighbours"].is_array()) RefuseRecord(at, frame + "neighbours are not an array");
    for (const nlohmann::json& n : f["neighbours"]) {
      if (!n.is_number_integer()) RefuseRecord(at, frame + "neighbours are not frame indices");
      p.neighbours.push_back(n.get<int64_t>());
    }
  }
  return p;
}

// The first `max_frames` placements of the frozen frames' file, of its first `bytes` bytes
// (what a manifest counts).
std::vector<FramePlacement> ReadFrozenRecord(const std::string& log, uintmax_t bytes,
                                             size_t max_frames) {
  std::vector<FramePlacement> placements;
  std::string text(static_cast<size_t>(bytes), '\0');
  if (bytes > 0) {
    std::ifstream in(log, std::ios::binary);
    in.read(text.data(), static_cast<std::streamsize>(bytes));
    if (!in) RefuseRecord({log, 0, 0, ""}, "cannot be read");
  }
  size_t start = 0;
  for (int line = 1; start < text.size() && placements.size() < max_frames; ++line) {
    const size_t end = text.find('\n', start);
    if (end == std::string::npos) RefuseRecord({log, line, 0, ""}, "the line is cut short");
    const nlohmann::json f =
        nlohmann::json::parse(text.begin() + static_cast<std::ptrdiff_t>(start),
                              text.begin() + static_cast<std::ptrdiff_t>(end), nullptr, false);
    placements.push_back(ParsePlacementRecord(f, {log, line, 0, ""}));
    start = end + 1;
  }
  return placements;
}

// The resume record as read back, and how much of the frozen frames' file it covers.
struct ResumeRecord {
  FusionResumeState state;
  size_t frozen_frames = 0;
  uintmax_t frozen_bytes = 0;
};

// Reads the resume record a run stored under "fusion" in its application state (and the
// frozen frames' file it counts); throws InputError naming the file, the field or line and the
// frame for anything missing, of the wrong type or not finite.
ResumeRecord ParseResumeRecord(const nlohmann::json& doc, const std::filesystem::path& store) {
  const std::string manifest = (store / "manifest.json").string();
  const SourceLocation top{manifest, 0, 0, "application.fusion."};
  if (!doc.is_object()) RefuseRecord(top, "the resume record is not a JSON object");
  const int64_t version = RecordInteger(doc, "version", top);
  if (version > kResumeRecordVersion) {
    throw InputError({manifest, 0, 0, "application.fusion.version"},
                     "the resume record has version " + std::to_string(version) +
                         ", newer than this irmosaic reads (" +
                         std::to_string(kResumeRecordVersion) + ")",
                     "resume with the irmosaic that wrote the store");
  }
  ResumeRecord record;
  FusionResumeState& state = record.state;
  if (doc.contains("frozen")) {
    SourceLocation at = top;
    at.field += "frozen.";
    const int64_t frames = RecordInteger(doc["frozen"], "frames", at);
    const int64_t bytes = RecordInteger(doc["frozen"], "bytes", at);
    const std::string log = (store / kFrozenRecordFile).string();
    std::error_code error;  // Nothing frozen yet: the file need not exist.
    const uintmax_t size = bytes > 0 ? std::filesystem::file_size(log, error) : 0;
    if (frames < 0 || bytes < 0 || error || size < static_cast<uintmax_t>(bytes)) {
      RefuseRecord({log, 0, 0, ""},
                   "holds " + (error ? std::string("nothing") : std::to_string(size) + " bytes") +
                       " but the manifest's resume record counts " + std::to_string(bytes) +
                       " bytes of " + std::to_string(frames) + " frames");
    }
    state.placements = ReadFrozenRecord(log, static_cast<uintmax_t>(bytes), SIZE_MAX);
    if (state.placements.size() != static_cast<size_t>(frames)) {
      RefuseRecord({log, 0, 0, ""}, "holds " + std::to_string(state.placements.size()) +
                                        " frames in its first " + std::to_string(bytes) +
                                        " bytes but the manifest counts " + std::to_string(frames));
    }
    record.frozen_frames = state.placements.size();
    record.frozen_bytes = static_cast<uintmax_t>(bytes);
  }
  if (!doc.contains("frames") || !doc["frames"].is_array()) {
    RefuseRecord({manifest, 0, 0, "application.fusion.frames"}, "frames is not an array");
  }
  const nlohmann::json& frames = doc["frames"];
  for (size_t k = 0; k < frames.size(); ++k) {
    const SourceLocation at{manifest, 0, 0,
                            "application.fusion.frames[" + std::to_string(k) + "]."};
    state.placements.push_back(ParsePlacementRecord(frames[k], at));
    if (!frames[k].contains("painted")) continue;  // Painted at its placement (or older record).
    const nlohmann::json& painted = frames[k]["painted"];
    SourceLocation in = at;
    in.field += "painted.";
    const std::string frame = "frame " + std::to_string(state.placements.back().index) + "'s ";
    if (!painted.is_object()) RefuseRecord(in, frame + "painted placement is not an object");
    state.painted.push_back({state.placements.back().index,
                             RecordMatrix(painted, "h", in, frame + "painted placement"),
                             RecordFinite(painted, "gain", in, frame + "painted gain"),
                             RecordFinite(painted, "offset", in, frame + "painted offset")});
  }
  state.held_from = RecordInteger(doc, "held_from", top);
  state.frames_since_solve = RecordInteger(doc, "frames_since_solve", top);
  state.solving_through = RecordInteger(doc, "solving_through", top);
  const SourceLocation pairs{manifest, 0, 0, "application.fusion.pairs"};
  if (!doc.contains("pairs") || !doc["pairs"].is_array()) {
    RefuseRecord(pairs, "pairs is not an array");
  }
  for (const nlohmann::json& p : doc["pairs"]) {
    if (!p.is_array() || p.size() != 3 || !p[0].is_number_integer() || !p[1].is_number_integer() ||
        !p[2].is_number() || !std::isfinite(p[2].get<double>())) {
      RefuseRecord(pairs, "a pair is not [base, template, weight] with a finite weight");
    }
    state.pairs.push_back({p[0].get<int64_t>(), p[1].get<int64_t>(), p[2].get<double>()});
  }
  return record;
}

// Undistorted image pixel of an orthoimage pixel.
Eigen::Vector2d ImageFromOrtho(const OrthoImage& ortho, const Eigen::Vector2d& p) {
  return ApplyHomography(ortho.ortho_from_image.inverse(), p);
}

}  // namespace

std::array<double, 6> WindowGeoTransform(double gsd_m, cv::Point top_left_px) {
  return {(top_left_px.x - 0.5) * gsd_m, gsd_m, 0.0, -(top_left_px.y - 0.5) * gsd_m, 0.0, -gsd_m};
}

bool MosaickerOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& text) {
    if (error) *error = text;
    return false;
  };
  if (store_path.empty()) return fail("store_path is empty: name the output store folder");
  if (!(gsd_m >= 0.0) || !std::isfinite(gsd_m)) return fail("gsd_m must be >= 0 (0: automatic)");
  if (!(pos_position_sigma_m > 0.0)) return fail("pos_position_sigma_m must be positive");
  if (!(pos_attitude_sigma_deg > 0.0)) return fail("pos_attitude_sigma_deg must be positive");
  if (!(search_radius_px >= 4.0 && search_radius_px <= 1024.0))
    return fail("search_radius_px must be in [4, 1024]");
  if (!(wide_search_radius_px == 0.0 ||
        (wide_search_radius_px >= search_radius_px && wide_search_radius_px <= 1024.0))) {
    return fail("wide_search_radius_px must be 0 (no second try) or in [search_radius_px, 1024]");
  }
  if (!(publish_interval_s > 0.0) || !std::isfinite(publish_interval_s)) {
    return fail("publish_interval_s must be a positive number of seconds");
  }
  if (registration_threads < 1 || registration_threads > 64) {
    return fail("registration_threads must be in 1..64");
  }
  if (heap_trim_interval_frames < 0) return fail("heap_trim_interval_frames must be >= 0");
  if (writer_nice < 0 || writer_nice > 19) {
    return fail("writer_nice " + std::to_string(writer_nice) + " must be in 0..19");
  }
  if (refresh_slice_tiles < 0) return fail("refresh_slice_tiles must be >= 0");
  if (!(sync_interval_s >= 0.0) || !std::isfinite(sync_interval_s)) {
    return fail("sync_interval_s must be >= 0 seconds");
  }
  if (refresh_quiet_publishes < 1 || refresh_quiet_publishes > 1000) {
    return fail("refresh_quiet_publishes must be in 1..1000");
  }
  if (max_cached_tiles < 1 || max_cached_tiles > 65536) {
    return fail("max_cached_tiles must be in 1..65536");
  }
  if (images_in_memory < 0) return fail("images_in_memory must be >= 0 (0: all in memory)");
  if (!(overview_interval_s >= 0.0)) return fail("overview_interval_s must be >= 0");
  if (!(max_range_m > 0.0)) return fail("max_range_m must be positive");
  if (std::isnan(origin_lat_deg) != std::isnan(origin_lon_deg)) {
    return fail("origin_lat_deg and origin_lon_deg: set both or neither (NaN: the first POS)");
  }
  if (!std::isnan(origin_lat_deg) &&
      !(std::abs(origin_lat_deg) < 89.0 && std::abs(origin_lon_deg) <= 180.0)) {
    return fail("origin_lat_deg must be in (-89, 89) and origin_lon_deg in [-180, 180] degrees");
  }
  // The store's own rules (tile size, compression), checked here so that a bad value is
  // refused at construction, not at the first placed frame.
  TileStoreOptions store;
  store.path = store_path;
  store.tile_size = tile_size;
  store.compression = compression;
  std::string store_error;
  if (!store.IsValid(&store_error)) return fail(store_error);
  std::string fusion_error;
  if (!fusion.IsValid(&fusion_error)) return fail("fusion: " + fusion_error);
  std::string registration_error;
  if (!registration.IsValid(&registration_error)) {
    return fail("registration: " + registration_error);
  }
  return true;
}

class Mosaicker::Impl : public MosaicSink {
 public:
  Impl(MosaickerOptions options, CameraModel camera, PosTrack pos)
      : options_(std::move(options)),
        camera_(std::move(camera)),
        pos_(std::move(pos)),
        ground_(options_.ground_height_m),
        ortho_(camera_) {
    std::string error;
    if (!options_.IsValid(&error)) {
      throw InputError({"options", 0, 0, ""}, error, "correct the option");
    }
#if defined(__GLIBC__)
    if (options_.tune_heap) {
      // MosaickerOptions::tune_heap. 32 MiB is glibc's largest mmap threshold on 64 bits.
      mallopt(M_MMAP_THRESHOLD, 32 << 20);
      mallopt(M_TRIM_THRESHOLD, 1 << 30);
    }
#endif
    if (pos_.empty() && (std::isnan(options_.origin_lat_deg) ||
                         std::isnan(options_.origin_lon_deg) || options_.gsd_m == 0.0)) {
      throw InputError({"options", 0, 0, "origin_lat_deg"},
                       "the POS track is empty, so the origin and GSD cannot come from it",
                       "set origin_lat_deg, origin_lon_deg and gsd_m, or give a POS track");
    }
    const double lat0 = std::isnan(options_.origin_lat_deg) ? pos_.records().front().lat_deg
                                                            : options_.origin_lat_deg;
    const double lon0 = std::isnan(options_.origin_lon_deg) ? pos_.records().front().lon_deg
                                                            : options_.origin_lon_deg;
    frame_ = std::make_unique<LocalFrame>(lat0, lon0);
    double gsd = options_.gsd_m;
    if (gsd == 0.0) {
      const PosRecord& first = pos_.records().front();
      const double above_ground = first.height_m - options_.ground_height_m;
      if (!(above_ground > 1.0)) {
        throw InputError({"POS", 1, 0, "height_m"},
                         "the first POS record is not above the ground height",
                         "give --ground-height in ellipsoidal metres, or --gsd");
      }
      gsd = RoundSignificant(above_ground / camera_.fx, 3);
    }
    grid_ = MosaicGrid{gsd};
    georef_ = {lat0, lon0, gsd, frame_->CrsWkt()};
    if (options_.planned_extent) planned_px_ = PlannedBoundsPx();
    registration_ = options_.registration;
    FusionOptions fusion = options_.fusion;
    fusion.registration_threads = options_.registration_threads;  // Register() is thread-safe.
    fusion.images_in_memory = options_.images_in_memory;
    fusion.spill_directory = options_.store_path;
    fusion_ = std::make_unique<MapFusion>(
        fusion, camera_,
        [this](const FusionFrame& base, const FusionFrame& templ) { return Register(base, templ); },
        this);
    // Resuming reads the pixel type from the store; a store killed before its first publish
    // has none yet, and is created at the first frame as a new one (TileStore::Open).
    if (options_.mode == TileStoreOptions::Mode::kResume &&
        std::filesystem::exists(std::filesystem::path(options_.store_path) / "manifest.json")) {
      OpenStore(PixelType::kUInt16);
    }
  }

  ~Impl() override {
    fusion_.reset();  // Joins the optimizer before the store goes.
  }

  PushResult Push(int64_t index, double time_s, const Pose* given_pose, const cv::Mat& image,
                  Clock::time_point arrival) {
    PushResult result;
    Count(&MosaickerSummary::frames_pushed);
    if (options_.heap_trim_interval_frames > 0 &&
        ++pushed_since_trim_ >= options_.heap_trim_interval_frames) {
      pushed_since_trim_ = 0;
#if defined(__GLIBC__)
      malloc_trim(0);
#endif
    }
    auto skip = [&](const std::string& reason) {
      result.reason =
          "frame " + std::to_string(index) + " (time " + Format(time_s) + " s): " + reason;
      Count(&MosaickerSummary::frames_skipped);
      return result;
    };
    if (image.empty() || image.channels() != 1 ||
        (image.depth() != CV_8U && image.depth() != CV_16U && image.depth() != CV_32F)) {
      return skip("the image is empty or not one channel of 8-bit, 16-bit or float");
    }
    if (image.cols != camera_.width || image.rows != camera_.height) {
      return skip("the image is " + std::to_string(image.cols) + "x" + std::to_string(image.rows) +
                  " but the camera file says " + std::to_string(camera_.width) + "x" +
                  std::to_string(camera_.height));
    }
    if (store_ && CvDepthOf(store_->pixel_type()) != image.depth()) {
      return skip(std::string("its bit depth differs from the store's (") +
                  GdalTypeNameOf(store_->pixel_type()) + ")");
    }
    PoseLookup pose;
    if (given_pose != nullptr) {
      pose.pose = *given_pose;
      if (!std::isfinite(pose.pose.lat_deg) || !std::isfinite(pose.pose.lon_deg) ||
          !std::isfinite(pose.pose.height_m) || std::abs(pose.pose.lat_deg) > 90.0 ||
          !pose.pose.ned_from_body.coeffs().allFinite() ||
          !pose.pose.body_from_mount.coeffs().allFinite() ||
          pose.pose.ned_from_body.norm() < 1e-9 || pose.pose.body_from_mount.norm() < 1e-9) {
        return skip("the given pose is not finite (position or attitude)");
      }
      pose.pose.ned_from_body.normalize();
      pose.pose.body_from_mount.normalize();
    } else {
      pose = pos_.At(time_s);
      if (!pose.ok()) return skip("no POS: " + pose.message);
    }
    GeometryOptions geometry_options;
    geometry_options.max_range_m = options_.max_range_m;
    const FrameGeometry geometry =
        ComputeFrameGeometry(camera_, pose.pose, *frame_, grid_, ground_, geometry_options);
    if (!geometry.ok) return skip(geometry.problem);
    FusionFrame frame;
    frame.index = index;
    frame.time_s = time_s;
    frame.image = HeldImageBuffer(image);
    image.copyTo(frame.image);
    frame.pos_mosaic_from_image = geometry.mosaic_from_image;
    frame.image_clip = geometry.image_clip;
    if (!geometry.image_clip.empty()) {
      std::lock_guard<std::mutex> lock(mu_);
      clips_[index] = geometry.image_clip;
    }
    if (!geometry.warning.empty()) {
      result.warning = "frame " + std::to_string(index) + ": " + geometry.warning;
    }
    std::shared_ptr<OrthoImage> ortho;
    try {
      ortho = BuildPosOrtho(frame);
    } catch (const InputError& e) {
      return skip(e.problem());
    }
    // The fusion keeps its window's frames for minutes; their POS orthoimages (several times
    // the frame's size, oblique) serve only registration to the next frames, so they live in
    // a small cache here and the fusion's copy carries only the geometry.
    frame.pos_ortho.origin_px = ortho->origin_px;
    frame.pos_ortho.ortho_from_image = ortho->ortho_from_image;
    RememberOrtho(index, std::move(ortho));
    frame.prior_sqrt_information = PosPriorSqrtInformation(camera_, pose.pose, *frame_, grid_,
                                                           ground_, options_.pos_position_sigma_m,
                                                           options_.pos_attitude_sigma_deg, 0.2);
    if (!store_) OpenStore(PixelTypeOf(image));
    // A frame the resume record holds is a replay: counted when the record was read, and
    // nothing to publish (the store has it already).
    const bool recorded = resume_recorded_ && index <= resumed_last_index_;
    result.placement = fusion_->Push(std::move(frame));
    result.status = PushResult::Status::kPlaced;
    last_index_ = std::max(last_index_, index);
    if (!recorded) {
      Count(&MosaickerSummary::frames_placed);
      Count(result.placement.pos_only ? &MosaickerSummary::frames_pos_only
                                      : &MosaickerSummary::frames_registered);
    }
    // Publish on a clock: each frame waits at most one interval plus the writer's work.
    if (!recorded && !replay_) {
      pending_.push_back({arrival, 0, index});
      if (Clock::now() - last_publish_ >=
          std::chrono::duration<double>(options_.publish_interval_s)) {
        RequestPublishQuiet();
      }
    }
    CollectLatencies();
    NotifyPublished();
    return result;
  }

  void RequestPublish() {
    RequestPublishQuiet();
    NotifyPublished();
  }

  // Returns the generation requested (0 without a store). `update_resume_record` false keeps
  // the resume record of the last publish.
  int64_t RequestPublishQuiet(bool update_resume_record = true) {
    if (!store_) return 0;
    if (update_resume_record) store_->SetApplicationState(ApplicationState());
    const int64_t generation = store_->RequestPublish();
    for (PendingFrame& p : pending_) {
      if (p.generation == 0) p.generation = generation;
    }
    last_publish_ = Clock::now();
    return generation;
  }

  void Finish() {
    // The frames placed since the last publish go out, and OnPublished hears of them, before
    // the final solve (every frame of the window, re-rendering all that moved), which takes
    // seconds: the newest frames waited for it (the last frames of a 25 fps run reached the
    // disk 5-6 s after they arrived instead of 0.3-0.5 s; docs/benchmarks.md, "Session 16").
    if (store_ && !replay_ && !pending_.empty()) {
      // The resume record stays the last one published: a run killed during the final solve
      // resumes as one killed before Finish (it pushes the unrecorded frames again), not from
      // a state no run killed earlier passes through.
      const int64_t generation = RequestPublishQuiet(false);
      try {
        store_->WaitPublished(generation);
      } catch (const OutputError&) {
        // The writer failed (full disk): Close() below reports it, after the final solve.
      }
      CollectLatencies();
      NotifyPublished();
    }
    fusion_->Finish();
    if (!store_) return;
    RequestPublishQuiet();
    store_->Close();
    CollectLatencies();
    NotifyPublished();
  }

  void OnPublished(std::function<void(int64_t)> callback) { on_published_ = std::move(callback); }

  int64_t published_generation() const {
    const TileStore* store = StoreView();
    return store ? store->published_generation() : 0;
  }

  void WaitPublished(int64_t generation) {
    TileStore* store = StoreView();
    if (generation <= 0) return;
    if (!store) {
      throw OutputError("nothing can be published yet: no frame has been placed in " +
                        options_.store_path);
    }
    store->WaitPublished(generation);
  }

  std::vector<FrameRecord> FrameRecords() const {
    const TileStore* store = StoreView();
    return store ? store->FrameRecords() : std::vector<FrameRecord>();
  }

  cv::Rect bounds_px() const {
    const TileStore* store = StoreView();
    return store ? store->level0_bounds_px() : cv::Rect();
  }

  MosaicWindow ReadWindow(const cv::Rect& mosaic_px) const {
    const TileStore* store = StoreView();
    if (!store) {
      throw InputError({"ReadWindow", 0, 0, ""}, "no frame has been placed yet, so no mosaic",
                       "push a frame that is placed first");
    }
    constexpr int kMaxSide = 65536;
    if (mosaic_px.width <= 0 || mosaic_px.height <= 0 || mosaic_px.width > kMaxSide ||
        mosaic_px.height > kMaxSide) {
      throw InputError({"ReadWindow", 0, 0, "mosaic_px"},
                       "window " + std::to_string(mosaic_px.width) + " x " +
                           std::to_string(mosaic_px.height) + " pixels is not 1..65536 a side",
                       "read a smaller window (bounds_px() gives the painted extent)");
    }
    MosaicWindow window;
    window.mosaic_px = mosaic_px;
    store->ReadWindow(mosaic_px, &window.image, &window.coverage);
    window.geotransform = WindowGeoTransform(grid_.gsd_m, mosaic_px.tl());
    window.crs_wkt = georef_.crs_wkt;
    return window;
  }

  const StoreGeoreference& georeference() const { return georef_; }

  MosaickerSummary summary() const {
    std::lock_guard<std::mutex> lock(mu_);
    MosaickerSummary s = summary_;
    s.fusion = fusion_->stats();
    s.gsd_m = grid_.gsd_m;
    s.origin_lat_deg = georef_.origin_lat_deg;
    s.origin_lon_deg = georef_.origin_lon_deg;
    if (store_) s.generations_published = store_->published_generation();
    if (!latencies_s_.empty()) {
      std::vector<double> sorted = latencies_s_;
      std::sort(sorted.begin(), sorted.end());
      auto at = [&](double q) {
        return sorted[std::min(sorted.size() - 1, static_cast<size_t>(q * sorted.size()))];
      };
      s.publish_latency_p50_s = at(0.5);
      s.publish_latency_p99_s = at(0.99);
      s.publish_latency_max_s = sorted.back();
    }
    return s;
  }

  // The released frames' placements from the frozen frames' file, then the fusion's.
  std::vector<FramePlacement> Placements() const {
    std::lock_guard<std::mutex> lock(frozen_mu_);
    std::vector<FramePlacement> placements;
    if (released_slots_ > 0) {
      placements = ReadFrozenRecord(
          (std::filesystem::path(options_.store_path) / kFrozenRecordFile).string(),
          frozen_record_bytes_, released_slots_);
    }
    std::vector<FramePlacement> held = fusion_->Placements();
    placements.insert(placements.end(), std::make_move_iterator(held.begin()),
                      std::make_move_iterator(held.end()));
    return placements;
  }

  void WritePlacements(const std::string& path) const {
    nlohmann::json frames = nlohmann::json::array();
    for (const FramePlacement& p : Placements()) {
      frames.push_back({{"index", p.index},
                        {"time_s", p.time_s},
                        {"mosaic_from_image", RowMajor(p.mosaic_from_image)},
                        {"pos_only", p.pos_only},
                        {"inliers", p.inliers},
                        {"residual_px", p.residual_px},
                        {"gain", p.gain},
                        {"offset", p.offset}});
    }
    const nlohmann::json doc = {
        {"origin", {{"lat_deg", georef_.origin_lat_deg}, {"lon_deg", georef_.origin_lon_deg}}},
        {"gsd_m", grid_.gsd_m},
        {"frames", frames}};
    const std::string tmp = path + ".tmp";
    {
      std::ofstream out(tmp);
      out << std::setprecision(17) << doc.dump(1) << "\n";
      if (!out) throw OutputError("cannot write " + tmp + " (disk full or not writable?)");
    }
    if (std::rename(tmp.c_str(), path.c_str()) != 0) {
      throw OutputError("cannot rename " + tmp + " to " + path);
    }
  }

  void SetReplay(bool replay) { replay_ = replay; }
  int64_t resumed_last_index() const { return resumed_last_index_; }
  int64_t resume_replay_from() const { return replay_from_; }
  const std::string& resume_warning() const { return resume_warning_; }
  TileStore* store() { return store_.get(); }

  // MosaicSink.
  void Paint(const cv::Mat& image, const cv::Mat& weight, cv::Point origin_px) override {
    if (replay_ || !store_) return;
    store_->Paint(image, weight, origin_px);
  }
  void Repaint(const cv::Mat& image, const cv::Mat& weight, cv::Point origin_px) override {
    if (replay_ || !store_) return;
    store_->Paint(image, weight, origin_px, PaintKind::kRefresh);
  }
  double OutputBacklogSeconds() const override {
    const TileStore* store = StoreView();
    return store ? store->BacklogSeconds() : 0.0;
  }
  void FramePlaced(const FramePlacement& placement) override {
    if (replay_) return;
    if (options_.on_frame_painted) options_.on_frame_painted(placement);
    if (!store_) return;
    FrameRecord record;
    record.index = placement.index;
    record.time_s = placement.time_s;
    const std::array<Eigen::Vector2d, 4> corners = {
        Eigen::Vector2d(-0.5, -0.5), Eigen::Vector2d(camera_.width - 0.5, -0.5),
        Eigen::Vector2d(camera_.width - 0.5, camera_.height - 0.5),
        Eigen::Vector2d(-0.5, camera_.height - 0.5)};
    std::vector<Eigen::Vector2d> clip;  // A clipped frame's footprint is its kept part's.
    {
      std::lock_guard<std::mutex> lock(mu_);
      const auto found = clips_.find(placement.index);
      if (found != clips_.end()) clip = found->second;
    }
    for (int k = 0; k < 4; ++k) {
      Eigen::Vector2d corner = corners[k];
      for (const Eigen::Vector2d& p : clip) {
        if (&p == &clip.front() || (p - corners[k]).norm() < (corner - corners[k]).norm()) {
          corner = p;
        }
      }
      record.footprint_m[k] =
          grid_.PlaneFromPixel(ApplyHomography(placement.mosaic_from_image, corner));
    }
    record.pos_only = placement.pos_only;
    record.residual_px = placement.residual_px;
    record.inliers = placement.inliers;
    record.status = placement.pos_only ? "pos_only" : "registered";
    store_->PutFrameRecord(record);
  }

 private:
  std::atomic<int> pushed_since_trim_{0};  // MosaickerOptions::heap_trim_interval_frames.

  void Count(int64_t MosaickerSummary::*counter) {
    std::lock_guard<std::mutex> lock(mu_);
    ++(summary_.*counter);
  }

  static std::string Format(double value) {
    std::ostringstream text;
    text << std::setprecision(10) << value;
    return text.str();
  }

  // What `--resume` needs, published with every generation: the last frame painted and the
  // resume record (every placement and the optimizer's state, docs/store.md). Frames that left
  // the fusion's window never change again: they go once into the frozen frames' file, which
  // is on disk (in the kernel's cache, as the tiles are) before the manifest counting them.
  std::string ApplicationState() {
    const FusionResumeState state = fusion_->ResumeState(frozen_record_frames_);
    std::string frozen, moving;
    size_t newly_frozen = 0;
    std::map<int64_t, const FusionResumeState::Painted*> painted;
    for (const FusionResumeState::Painted& p : state.painted) painted[p.index] = &p;
    for (size_t k = 0; k < state.placements.size(); ++k) {
      nlohmann::json record = PlacementRecord(state.placements[k]);
      const auto found = painted.find(state.placements[k].index);
      if (found != painted.end()) {
        // Held frames only (never frozen): where the disk shows it, if not at its placement.
        record["painted"] = {{"h", RowMajor(found->second->mosaic_from_image)},
                             {"gain", found->second->gain},
                             {"offset", found->second->offset}};
      }
      const std::string text = record.dump();
      if (state.first_slot + k < state.frozen_slots) {
        frozen += text + "\n";
        ++newly_frozen;
      } else {
        moving += (moving.empty() ? "" : ",") + text;
      }
    }
    if (newly_frozen > 0 && AppendFrozenRecord(frozen)) {
      // On disk now: the fusion and the frame clips need not keep them any more.
      std::lock_guard<std::mutex> lock(frozen_mu_);
      frozen_record_frames_ += newly_frozen;
      if (!options_.keep_placements_in_memory) {
        released_slots_ = fusion_->ReleasePlacements(frozen_record_frames_);
      }
      std::lock_guard<std::mutex> clips_lock(mu_);
      for (size_t k = 0; k < newly_frozen; ++k) clips_.erase(state.placements[k].index);
    } else if (newly_frozen > 0) {
      // Not written (full disk): the manifest carries them this time, the next publish retries.
      std::replace(frozen.begin(), frozen.end(), '\n', ',');
      moving = frozen + moving;
      if (moving.back() == ',') moving.pop_back();
    }
    nlohmann::json pairs = nlohmann::json::array();
    for (const FusionResumeState::Pair& p : state.pairs) {
      pairs.push_back({p.base, p.templ, p.weight});
    }
    const nlohmann::json fusion = {
        {"version", kResumeRecordVersion},
        {"frozen", {{"frames", frozen_record_frames_}, {"bytes", frozen_record_bytes_}}},
        {"held_from", state.held_from},
        {"frames_since_solve", state.frames_since_solve},
        {"solving_through", state.solving_through},
        {"pairs", pairs}};
    std::string text = fusion.dump();  // An object: the frames go in before its closing brace.
    text.pop_back();
    text += ",\"frames\":[" + moving + "]}";
    return "{\"last_index\":" + std::to_string(last_index_) + ",\"fusion\":" + text + "}";
  }

  // Appends lines to the frozen frames' file; false (and the file as it was) if they cannot
  // be written: the store's own publish reports the full disk (TileStore::WaitPublished).
  bool AppendFrozenRecord(const std::string& lines) {
    const std::filesystem::path path =
        std::filesystem::path(options_.store_path) / kFrozenRecordFile;
    std::lock_guard<std::mutex> lock(frozen_mu_);
    if (!frozen_record_.is_open()) frozen_record_.open(path, std::ios::binary | std::ios::app);
    frozen_record_ << lines;
    frozen_record_.flush();
    if (frozen_record_) {
      frozen_record_bytes_ += lines.size();
      return true;
    }
    frozen_record_.close();
    std::error_code error;
    std::filesystem::resize_file(path, frozen_record_bytes_, error);
    return false;
  }

  // The mosaic pixels the flight is expected to cover: the union of the POS footprints of its
  // records (at most one per 0.2 s of POS time, and the last), grown by three POS position
  // sigmas, and a tile, against the POS errors the registration corrects. Empty without POS.
  // Cost: one frame geometry (a 9 x 9 ray fit) per 0.2 s of POS, 18,000 for an hour's track,
  // once at construction (not measured at that length; the sample's 32 are not noticeable).
  cv::Rect PlannedBoundsPx() const {
    const std::vector<PosRecord>& records = pos_.records();
    GeometryOptions geometry_options;
    geometry_options.max_range_m = options_.max_range_m;
    double x0 = HUGE_VAL, y0 = HUGE_VAL, x1 = -HUGE_VAL, y1 = -HUGE_VAL;
    double last_time = -HUGE_VAL;
    for (size_t i = 0; i < records.size(); ++i) {
      const double t = records[i].time_s;
      if (t - last_time < 0.2 && i + 1 != records.size()) continue;
      last_time = t;
      const PoseLookup pose = pos_.At(t);
      if (!pose.ok()) continue;
      const FrameGeometry geometry =
          ComputeFrameGeometry(camera_, pose.pose, *frame_, grid_, ground_, geometry_options);
      if (!geometry.ok) continue;
      for (const Eigen::Vector2d& corner : geometry.footprint_m) {
        const Eigen::Vector2d px = grid_.PixelFromPlane(corner);
        x0 = std::min(x0, px.x());
        y0 = std::min(y0, px.y());
        x1 = std::max(x1, px.x());
        y1 = std::max(y1, px.y());
      }
    }
    if (!(x0 < x1 && y0 < y1)) return {};
    const double margin = 3.0 * options_.pos_position_sigma_m / grid_.gsd_m + options_.tile_size;
    static constexpr double kLimit = 1 << 29;  // Beyond GDAL's raster sizes anyway.
    const auto clamp = [](double v) { return std::clamp(v, -kLimit, kLimit); };
    const int left = static_cast<int>(clamp(std::floor(x0 - margin)));
    const int top = static_cast<int>(clamp(std::floor(y0 - margin)));
    const int right = static_cast<int>(clamp(std::ceil(x1 + margin)));
    const int bottom = static_cast<int>(clamp(std::ceil(y1 + margin)));
    return {left, top, right - left, bottom - top};
  }

  void OpenStore(PixelType type) {
    TileStoreOptions store_options;
    store_options.path = options_.store_path;
    store_options.mode = options_.mode;
    store_options.tile_size = options_.tile_size;
    store_options.compression = options_.compression;
    store_options.overview_interval_s = options_.overview_interval_s;
    store_options.max_cached_tiles = static_cast<size_t>(options_.max_cached_tiles);
    store_options.refresh_slice_tiles = options_.refresh_slice_tiles;
    store_options.refresh_quiet_publishes = options_.refresh_quiet_publishes;
    store_options.writer_nice = options_.writer_nice;
    store_options.sync_interval_s = options_.sync_interval_s;
    store_options.on_publish = options_.on_publish;
    store_options.pixel_type = type;
    std::unique_ptr<TileStore> opened = TileStore::Open(store_options, georef_);
    if (!planned_px_.empty()) opened->SetPlannedBoundsPx(planned_px_);
    {
      std::lock_guard<std::mutex> lock(mu_);  // Other threads read store_ through StoreView().
      store_ = std::move(opened);
    }
    if (options_.mode == TileStoreOptions::Mode::kResume) {
      const std::string state = store_->application_state();
      if (!state.empty()) {
        const nlohmann::json doc = nlohmann::json::parse(state, nullptr, false);
        if (doc.is_object() && doc.contains("last_index") && doc["last_index"].is_number()) {
          resumed_last_index_ = doc["last_index"].get<int64_t>();
        }
        if (resumed_last_index_ >= 0 && doc.contains("fusion")) {
          Resume(ParseResumeRecord(doc["fusion"], options_.store_path));
        } else if (resumed_last_index_ >= 0) {
          replay_from_ =
              std::max<int64_t>(0, resumed_last_index_ - options_.fusion.window_frames + 1);
          resume_warning_ = options_.store_path +
                            " has no resume record (written by an irmosaic before 2026-12-01): "
                            "the frames before " +
                            std::to_string(replay_from_) +
                            " keep their tiles but not their placements (they are missing from "
                            "placements.json), and the replayed ones may differ from an "
                            "uninterrupted run";
        }
      }
      last_index_ = resumed_last_index_;
    }
    // The frozen frames' file holds what the manifest counts and nothing after it (a run killed
    // between an append and its publish left lines no manifest counts).
    const std::filesystem::path log =
        std::filesystem::path(options_.store_path) / kFrozenRecordFile;
    std::error_code error;
    if (frozen_record_bytes_ > 0) {
      std::filesystem::resize_file(log, frozen_record_bytes_, error);
    } else {
      std::filesystem::remove(log, error);
    }
    if (error) throw OutputError("cannot truncate " + log.string() + ": " + error.message());
  }

  // Seeds the fusion from the store's resume record.
  void Resume(ResumeRecord record) {
    frozen_record_frames_ = record.frozen_frames;
    frozen_record_bytes_ = record.frozen_bytes;
    FusionResumeState& state = record.state;
    replay_from_ = state.ReplayFrom();
    if (replay_from_ < 0) replay_from_ = resumed_last_index_ + 1;  // Nothing held: no replay.
    {
      std::lock_guard<std::mutex> lock(mu_);
      for (const FramePlacement& p : state.placements) {
        ++summary_.frames_placed;
        ++(p.pos_only ? summary_.frames_pos_only : summary_.frames_registered);
      }
    }
    if (!options_.keep_placements_in_memory) {
      // The frozen frames stay in their file: the fusion holds the frames from the first one
      // not frozen, or the replay's first one if older (push order is index order), on.
      size_t keep = std::min(record.frozen_frames, state.placements.size());
      const int64_t from = state.ReplayFrom();
      while (from >= 0 && keep > 0 && state.placements[keep - 1].index >= from) --keep;
      for (size_t k = 0; k < keep; ++k) {
        ++(state.placements[k].pos_only ? state.released_pos_only : state.released_registered);
      }
      state.placements.erase(state.placements.begin(),
                             state.placements.begin() + static_cast<std::ptrdiff_t>(keep));
      state.first_slot = keep;
      std::lock_guard<std::mutex> lock(frozen_mu_);
      released_slots_ = keep;
    }
    fusion_->Resume(std::move(state));
    resume_recorded_ = true;
  }

  // Keeps a frame's POS orthoimage for registration to the frames after it (bounded).
  void RememberOrtho(int64_t index, std::shared_ptr<const OrthoImage> ortho) {
    std::lock_guard<std::mutex> lock(ortho_mu_);
    ortho_cache_.emplace_back(index, std::move(ortho));
    while (ortho_cache_.size() > kOrthoCacheFrames) ortho_cache_.pop_front();
  }

  // The POS orthoimage of a fusion frame: cached, or rebuilt (the same pixels) when it left
  // the cache, e.g. a neighbour from an earlier pass over the same ground.
  std::shared_ptr<const OrthoImage> PosOrtho(const FusionFrame& frame) {
    {
      std::lock_guard<std::mutex> lock(ortho_mu_);
      for (auto it = ortho_cache_.rbegin(); it != ortho_cache_.rend(); ++it) {
        if (it->first == frame.index) return it->second;
      }
    }
    return BuildPosOrtho(frame);
  }

  // A buffer for the copy of a pushed image the fusion holds: from the pool when the image has
  // the size and type of the flight's first (those of one camera), otherwise its own.
  cv::Mat HeldImageBuffer(const cv::Mat& image) {
    if (!held_pool_) {
      const FusionOptions& fusion = options_.fusion;
      const size_t frames =
          static_cast<size_t>(std::max({fusion.window_frames, fusion.candidate_frames, 1}));
      // A solve holds its window's images a little longer; a few more for a running one.
      held_pool_ = std::make_unique<MatPool>(image.rows, image.cols, image.type(), frames + 64);
    }
    if (!held_pool_->Fits(image.rows, image.cols, image.type())) {
      return cv::Mat(image.rows, image.cols, image.type());
    }
    return held_pool_->Take();
  }

  // A frame's POS orthoimage, built the same way when it is pushed and again when registration
  // needs it after it left the cache (until session 5 the rebuild left out the clip polygon, so
  // a frame clipped at max_range_m registered with ground it does not show).
  std::shared_ptr<OrthoImage> BuildPosOrtho(const FusionFrame& frame) {
    auto ortho = std::make_shared<OrthoImage>();
    std::lock_guard<std::mutex> lock(ortho_build_mu_);  // ortho_'s scratch; pairs run at once.
    ortho_.Run(frame.image, frame.pos_mosaic_from_image, ortho.get(), frame.image_clip);
    return ortho;
  }

  // SCD + fast LSM + RANSAC between the POS orthoimages; tie points back to image pixels.
  PairMatch Register(const FusionFrame& base_frame, const FusionFrame& templ_frame) {
    PairMatch match;
    const std::shared_ptr<const OrthoImage> base_ortho = PosOrtho(base_frame);
    const std::shared_ptr<const OrthoImage> templ_ortho = PosOrtho(templ_frame);
    const OrthoImage& base = *base_ortho;
    const OrthoImage& templ = *templ_ortho;
    const Eigen::Vector2d predicted(templ.origin_px.x - base.origin_px.x,
                                    templ.origin_px.y - base.origin_px.y);
    // A registrar of the pool (scratch buffers are per registrar): pairs run at once.
    std::unique_ptr<PairRegistrar> registrar;
    {
      std::lock_guard<std::mutex> lock(registrar_mu_);
      if (!registrars_.empty()) {
        registrar = std::move(registrars_.back());
        registrars_.pop_back();
      }
    }
    if (!registrar) registrar = std::make_unique<PairRegistrar>(registration_);
    double radius = options_.search_radius_px;
    PairRegistration r =
        registrar->Register(base.image, base.mask, templ.image, templ.mask, predicted, radius);
    if (!r.ok() && r.status != PairRegistration::Status::kBadInput &&
        options_.wide_search_radius_px > radius) {
      // The true offset may lie outside the first radius: once more, searching wider.
      radius = options_.wide_search_radius_px;
      r = registrar->Register(base.image, base.mask, templ.image, templ.mask, predicted, radius);
    }
    {
      std::lock_guard<std::mutex> lock(registrar_mu_);
      registrars_.push_back(std::move(registrar));
    }
    if (options_.on_pair_registered) {
      PairRegistrationRecord record;
      record.base_index = base_frame.index;
      record.template_index = templ_frame.index;
      record.base = &base;
      record.templ = &templ;
      record.predicted_offset = predicted;
      record.search_radius_px = radius;
      record.result = &r;
      options_.on_pair_registered(record);
    }
    if (!r.ok()) {
      match.reason = std::string(ToString(r.status)) + ": " + r.reason;
      return match;
    }
    match.ok = true;
    match.residual_rms_px = r.residual_rms_px;
    match.base_from_template =
        base.ortho_from_image.inverse() * r.base_from_template * templ.ortho_from_image;
    // Tie points for the optimizer from the pair's homography, on a grid over the overlap
    // (both masks): evenly spread whatever the key points were, and as many as the
    // homography's own accuracy supports. Its accuracy at the overlap's corners is the joint
    // fit's predicted sigma (or the RANSAC residual); spreading that information over n
    // points inflates each point's sigma by sqrt(n / 4).
    std::vector<Eigen::Vector2d> in_template, in_base;
    const cv::Mat& tm = templ.mask;
    const cv::Mat& bm = base.mask;
    constexpr int kStep = 24;
    for (int y = kStep / 2; y < tm.rows; y += kStep) {
      for (int x = kStep / 2; x < tm.cols; x += kStep) {
        if (tm.at<uint8_t>(y, x) == 0) continue;
        const Eigen::Vector2d q = ApplyHomography(r.base_from_template, {x, y});
        const int bx = static_cast<int>(std::lround(q.x())),
                  by = static_cast<int>(std::lround(q.y()));
        if (bx < 0 || by < 0 || bx >= bm.cols || by >= bm.rows || bm.at<uint8_t>(by, bx) == 0) {
          continue;
        }
        in_template.emplace_back(x, y);
        in_base.push_back(q);
      }
    }
    if (in_template.size() < 4) {
      match.ok = false;
      match.reason = "the registered overlap is too small for tie points";
      return match;
    }
    const double sigma_h = r.joint_patches > 0
                               ? r.joint_sigma_px
                               : r.residual_rms_px / std::sqrt(std::max(1, r.inliers / 4));
    match.tie_sigma_px =
        std::max(0.05, sigma_h) * std::sqrt(static_cast<double>(in_template.size()) / 4.0);
    for (size_t k = 0; k < in_template.size(); ++k) {
      match.template_points.push_back(ImageFromOrtho(templ, in_template[k]));
      match.base_points.push_back(ImageFromOrtho(base, in_base[k]));
    }
    return match;
  }

  TileStore* StoreView() const {
    std::lock_guard<std::mutex> lock(mu_);
    return store_.get();
  }

  // Producer thread only: tells the callback about generations published since the last call.
  void NotifyPublished() {
    if (!on_published_ || !store_) return;
    const int64_t published = store_->published_generation();
    if (published <= notified_generation_) return;
    notified_generation_ = published;
    on_published_(published);
  }

  void CollectLatencies() {
    if (!store_) return;
    const int64_t published = store_->published_generation();
    const auto now = Clock::now();
    std::vector<std::pair<int64_t, double>> reported;  // For on_frame_published, unlocked.
    {
      std::lock_guard<std::mutex> lock(mu_);
      while (!pending_.empty() && pending_.front().generation != 0 &&
             pending_.front().generation <= published) {
        // From the frame's arrival to the end of the publish that put it on disk (not to this
        // call, which may come much later, e.g. after Finish's final solve).
        const auto at = store_->PublishedAt(pending_.front().generation);
        const double latency_s =
            std::chrono::duration<double>(at.value_or(now) - pending_.front().arrival).count();
        latencies_s_.push_back(latency_s);
        if (options_.on_frame_published) reported.push_back({pending_.front().index, latency_s});
        pending_.pop_front();
      }
      if (latencies_s_.size() > 200000)
        latencies_s_.erase(latencies_s_.begin(), latencies_s_.begin() + 100000);
    }
    for (const auto& [index, latency_s] : reported) options_.on_frame_published(index, latency_s);
  }

  MosaickerOptions options_;
  CameraModel camera_;
  PosTrack pos_;
  FlatGround ground_;
  cv::Rect planned_px_;  // The flight's extent foreseen from POS (PlannedBoundsPx); empty: none.
  std::unique_ptr<LocalFrame> frame_;
  MosaicGrid grid_;
  StoreGeoreference georef_;
  Orthorectifier ortho_;
  std::mutex ortho_build_mu_;  // Guards ortho_ (BuildPosOrtho).
  PairRegistrationOptions registration_;
  // Idle registrars, one per pair registered at once (MosaickerOptions::registration_threads).
  std::mutex registrar_mu_;
  std::vector<std::unique_ptr<PairRegistrar>> registrars_;
  // Frames' POS orthoimages, newest last: two sweeps of the default flight and some margin.
  static constexpr size_t kOrthoCacheFrames = 24;
  std::mutex ortho_mu_;
  std::deque<std::pair<int64_t, std::shared_ptr<const OrthoImage>>> ortho_cache_;
  std::unique_ptr<TileStore> store_;
  std::unique_ptr<MapFusion> fusion_;
  // Buffers of the images the fusion holds (~window_frames of them, each kept for as many
  // frames): pooled, not allocated per frame among the frame's short-lived buffers.
  std::unique_ptr<MatPool> held_pool_;
  bool replay_ = false;
  int64_t last_index_ = -1;
  int64_t resumed_last_index_ = -1;
  int64_t replay_from_ = -1;      // First frame a resume pushes again (-1: not resuming).
  bool resume_recorded_ = false;  // The fusion was seeded from the store's resume record.
  std::string resume_warning_;
  // The frozen frames' file (kFrozenRecordFile), how many frames (the first ones in push
  // order) and bytes it holds.
  // The frozen frames' file (resume record) and the placements the fusion released because
  // they are in it (MosaickerOptions::keep_placements_in_memory): frames [0, released_slots_)
  // in push order. frozen_mu_ guards the file's size and released_slots_ against Placements().
  mutable std::mutex frozen_mu_;
  std::ofstream frozen_record_;
  size_t frozen_record_frames_ = 0;
  uintmax_t frozen_record_bytes_ = 0;
  size_t released_slots_ = 0;
  Clock::time_point last_publish_ = Clock::now();
  mutable std::mutex mu_;
  std::map<int64_t, std::vector<Eigen::Vector2d>> clips_;  // Kept part of clipped frames.
  struct PendingFrame {
    Clock::time_point arrival;
    int64_t generation = 0;  // The publish that carries it; 0: none asked for yet.
    int64_t index = 0;
  };
  std::deque<PendingFrame> pending_;
  std::vector<double> latencies_s_;
  MosaickerSummary summary_;
  std::function<void(int64_t)> on_published_;
  int64_t notified_generation_ = 0;
};

Mosaicker::Mosaicker(MosaickerOptions options, CameraModel camera, PosTrack pos)
    : impl_(std::make_unique<Impl>(std::move(options), std::move(camera), std::move(pos))) {}
Mosaicker::~Mosaicker() = default;
PushResult Mosaicker::Push(int64_t index, double time_s, const cv::Mat& image) {
  return impl_->Push(index, time_s, nullptr, image, Clock::now());
}
PushResult Mosaicker::Push(int64_t index, double time_s, const cv::Mat& image,
                           std::chrono::steady_clock::time_point arrival) {
  return impl_->Push(index, time_s, nullptr, image, arrival);
}
PushResult Mosaicker::Push(int64_t index, double time_s, const Pose& pose, const cv::Mat& image) {
  return impl_->Push(index, time_s, &pose, image, Clock::now());
}
void Mosaicker::OnPublished(std::function<void(int64_t generation)> callback) {
  impl_->OnPublished(std::move(callback));
}
int64_t Mosaicker::published_generation() const { return impl_->published_generation(); }
void Mosaicker::WaitPublished(int64_t generation) { impl_->WaitPublished(generation); }
std::vector<FrameRecord> Mosaicker::FrameRecords() const { return impl_->FrameRecords(); }
cv::Rect Mosaicker::bounds_px() const { return impl_->bounds_px(); }
MosaicWindow Mosaicker::ReadWindow(const cv::Rect& mosaic_px) const {
  return impl_->ReadWindow(mosaic_px);
}
const StoreGeoreference& Mosaicker::georeference() const { return impl_->georeference(); }
void Mosaicker::SetReplay(bool replay) { impl_->SetReplay(replay); }
void Mosaicker::Finish() { impl_->Finish(); }
void Mosaicker::RequestPublish() { impl_->RequestPublish(); }
int64_t Mosaicker::resumed_last_index() const { return impl_->resumed_last_index(); }
int64_t Mosaicker::resume_replay_from() const { return impl_->resume_replay_from(); }
const std::string& Mosaicker::resume_warning() const { return impl_->resume_warning(); }
MosaickerSummary Mosaicker::summary() const { return impl_->summary(); }
std::vector<FramePlacement> Mosaicker::Placements() const { return impl_->Placements(); }
void Mosaicker::WritePlacements(const std::string& path) const { impl_->WritePlacements(path); }
TileStore* Mosaicker::store() { return impl_->store(); }

}  // namespace irmosaic
