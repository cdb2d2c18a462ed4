// End to end benchmark of the pipeline (issue 10; output cost of issue 7): the Mosaicker on a
// simulated 640x512 flight rendered on the fly by FlightSimulator (no disk input), and on the
// same first frames cv::Stitcher (SCANS) and a plain ORB+RANSAC incremental pipeline.
//
//   flight_bench [--frames N] [--paced-frames N] [--compare 100,300] [--no-compare]
//                [--no-optimize] [--store DIR] [--json FILE] [--timeout S]
//                [--publish-interval S] [--max-rerenders N] [--rerender-threshold PX]
//                [--settled-rerender-threshold PX] [--settled-rerenders] [--window N]
//                [--short-window N] [--full-every N] [--solve-every N] [--solve-iterations N]
//                [--sparse-library SUITE_SPARSE|EIGEN_SPARSE]
//                [--registration-threads N] [--max-neighbours N]
//                [--ground-cache-mb N]
//                [--lsm-level N] [--seed N] [--first N] [--bit-depth 8|16]
//                [--malloc-info DIR] [--exit-before-finish]
//
// The tuning options override the MosaickerOptions defaults, so a trade-off (output cost
// against freshness on disk, optimizer cost against accuracy) is measured on the same frames.
// Each Mosaicker run also scores its final placements against the simulator's truth.
//
// Scenarios: (1) "free": frames pushed as fast as the pipeline takes them, throughput and
// memory at 10 %, 50 % and 100 % of the flight; (2) "paced": frames arriving at the sensor rate
// (25 fps), publish latency counted from each frame's arrival; (3) "compare": each method in
// its own child process (this program with --child) so its peak memory is its own.
// Frames are rendered by a producer thread; the pipeline's CPU time excludes it (thread CPU
// clocks), which the load of a shared machine does not inflate much.
#include <malloc.h>
#include <pthread.h>
#include <spawn.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <deque>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <limits>
#include <mutex>
#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/stitching.hpp>
#include <optional>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "../src/warp_bilinear.h"
#include "irmosaic/evaluator.h"
#include "irmosaic/mosaicker.h"
#include "irmosaic/simulator.h"
#include "test_data.h"

extern char** environ;

namespace {

using Clock = std::chrono::steady_clock;
using irmosaic::Mosaicker;
using irmosaic::MosaickerOptions;
using irmosaic::SimFrame;

double Seconds(timespec ts) {
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}
double ProcessCpuSeconds() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return Seconds(ts);
}
double ThreadCpuSeconds(pthread_t thread) {
  clockid_t id;
  if (pthread_getcpuclockid(thread, &id) != 0) return 0.0;
  timespec ts{};
  clock_gettime(id, &ts);
  return Seconds(ts);
}
double Since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

// Resident memory from /proc/self/status, MiB: "VmRSS" now, "VmHWM" peak.
double StatusMiB(const char* key) {
  std::ifstream in("/proc/self/status");
  std::string line;
  const std::string prefix = std::string(key) + ":";
  while (std::getline(in, line)) {
    if (line.rfind(prefix, 0) == 0) return std::stod(line.substr(prefix.size())) / 1024.0;
  }
  return 0.0;
}
// Resets the peak resident size (VmHWM) so each scenario reports its own peak.
void ResetPeakRss() { std::ofstream("/proc/self/clear_refs") << "5"; }

// glibc heap figures (mallinfo2, every arena), MiB: in use (incl. mmapped chunks) or free.
double HeapMiB(bool in_use) {
  const struct mallinfo2 m = mallinfo2();
  const size_t bytes = in_use ? m.uordblks + m.hblkhd : m.fordblks;
  return static_cast<double>(bytes) / 1048576.0;
}

// Overrides of MosaickerOptions defaults (negative: keep the default).
struct Tuning {
  double publish_interval_s = -1.0;
  double overview_interval_s = -1.0;
  int tile_size = -1;
  std::string compression;  // MosaickerOptions::compression ("": the default).
  int max_rerenders_per_solve = -1;
  double rerender_threshold_px = -1.0;
  double settled_rerender_threshold_px = -1.0;  // FusionOptions::settled_rerender_threshold_px.
  int rerender_settled = -1;                    // FusionOptions::rerender_settled_frames (0 / 1).
  int window_frames = -1;
  int solve_every_frames = -1;
  int short_window_frames = -1;  // FusionOptions::short_window_frames (-1: the default).
  int full_window_every = -1;    // FusionOptions::full_window_every (-1: the default).
  int solve_iterations = -1;     // FusionOptions::solve_iterations (-1: the default).
  std::string sparse_library;    // FusionOptions::sparse_library (empty: the default).
  int registration_threads = -1;
  int max_neighbours = -1;  // FusionOptions::max_neighbours (-1: the default).
  int optimizer_nice = -1;
  double max_output_backlog_s = -1.0;
  int writer_nice = -1;
  double sync_interval_s = -1.0;    // MosaickerOptions::sync_interval_s (-1: the default).
  int lsm_level = -1;               // MosaickerOptions::registration.fine.lsm_level.
  int keypoints_at_lsm_level = -1;  // ... .fine.keypoints_at_lsm_level (0 / 1).
  double max_pair_sigma_px = -1.0;  // ... .fine.max_joint_sigma_px (the pair accept criterion).
  double max_coarse_pair_sigma_px = -1.0;  // ... .fine.max_coarse_joint_sigma_px.
  double wide_radius_px = -1.0;            // MosaickerOptions::wide_search_radius_px (0: none).
  int heap_trim_interval_frames = -1;
  int tune_heap = -1;  // MosaickerOptions::tune_heap (0 / 1; -1: the library's default).
  int max_cached_tiles = -1;
  int refresh_slice_tiles = -1;
  int refresh_quiet_publishes = -1;
  int images_in_memory = -1;  // -1: the library's default.
  int ground_cache_mb = -1;   // The simulator's (the benchmark's input), not the pipeline's.
  // The simulated flight's seed (its noise, POS errors and fractal detail); 0 keeps the
  // sample flight's own. Another seed is another flight over the same ground: accuracy
  // comparisons of two builds over a few seeds tell a change from one flight's luck.
  uint64_t seed = 0;
  // The simulated frames' sample depth (8 or 16); 0 keeps the sample flight's (16). 8-bit frames
  // make a store of Byte tiles, a third of the disk of UInt16 here (234 against ~750 KiB per
  // frame): an hour of this flight (90,000 frames) takes ~65 GB of store at 16 bits.
  int bit_depth = 0;
  // The flight's first frame pushed: frames first .. first + frames - 1 of the same simulated
  // flight (the simulator renders any frame on its own), so a frame deep in a long flight can be
  // looked at again in minutes. 0: from the start.
  int first_frame = 0;
  // glibc's mmap threshold (mallopt M_MMAP_THRESHOLD) for the Mosaicker's processes; 0 leaves
  // glibc's default (a threshold that rises as large blocks are freed). Measured in session 8,
  // not adopted: docs/benchmarks.md. Takes effect with --heap-tuning 0 only: the Mosaicker's
  // own tuning (MosaickerOptions::tune_heap) sets the threshold when it is made.
  int64_t mmap_threshold = 0;
  // OpenCV's worker threads (cv::setNumThreads) for the whole process: the warps and filters of
  // every stage split over them. 2, the target machine's cores, by default.
  int cv_threads = 2;
  // Folder for glibc's malloc_info XML at each checkpoint (free chunks by size, per arena):
  // where the free memory the heap keeps sits, for the memory creep of long runs. Empty: none.
  std::string malloc_info_dir;
  // Leave the process right after the last Push, nothing freed, so that heaptrack's report of
  // what was never freed is the live heap of a streaming run (compare two flight lengths).
  bool exit_before_finish = false;
};
Tuning g_tuning;

irmosaic::SynthOptions FlightOptions(int frames) {
  irmosaic::SynthOptions options =
      irmosaic::SynthOptions::LoadJson(irmosaic::testing::SamplePath("sample_flight/flight.json"));
  options.frame_count = g_tuning.first_frame + frames;
  if (g_tuning.ground_cache_mb > 0) options.ground_cache_mb = g_tuning.ground_cache_mb;
  if (g_tuning.seed > 0) options.seed = g_tuning.seed;
  if (g_tuning.bit_depth > 0) options.sensor.bit_depth = g_tuning.bit_depth;
  return options;
}

// Renders frames in order on its own thread, at most `depth` ahead of the consumer; with a
// rate, frame i is released no earlier than start + i / rate (its arrival from the sensor).
class Producer {
 public:
  Producer(const irmosaic::FlightSimulator& sim, int first, int frames, double rate_hz,
           size_t depth)
      : sim_(sim), first_(first), frames_(frames), rate_hz_(rate_hz), depth_(depth) {
    start_ = Clock::now();
    thread_ = std::thread([this] { Loop(); });
  }
  ~Producer() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      stop_ = true;
    }
    cv_.notify_all();
    thread_.join();
  }
  // Next frame and its arrival time; false at the end.
  bool Next(SimFrame* frame, Clock::time_point* arrival) {
    std::unique_lock<std::mutex> lock(mu_);
    cv_.wait(lock, [&] { return !queue_.empty() || done_; });
    if (queue_.empty()) return false;
    *frame = std::move(queue_.front().first);
    *arrival = queue_.front().second;
    queue_.pop_front();
    cv_.notify_all();
    return true;
  }
  // CPU time of the rendering thread so far (its own clock while it runs, then its total).
  double cpu_s() {
    std::lock_guard<std::mutex> lock(mu_);
    return done_ ? final_cpu_s_ : ThreadCpuSeconds(thread_.native_handle());
  }
  size_t max_queue() const { return max_queue_; }
  Clock::time_point start() const { return start_; }

 private:
  void Loop() {
    pthread_setname_np(pthread_self(), "sim-render");
    for (int i = 0; i < frames_; ++i) {
      SimFrame frame = sim_.Render(first_ + i);
      Clock::time_point arrival = Clock::now();
      if (rate_hz_ > 0) {
        arrival = start_ + std::chrono::duration_cast<Clock::duration>(
                               std::chrono::duration<double>(i / rate_hz_));
        std::this_thread::sleep_until(arrival);
      }
      std::unique_lock<std::mutex> lock(mu_);
      // Paced frames are never held back: a slow pipeline lets them queue (as a sensor would).
      cv_.wait(lock, [&] { return stop_ || rate_hz_ > 0 || queue_.size() < depth_; });
      if (stop_) break;
      queue_.emplace_back(std::move(frame), arrival);
      max_queue_ = std::max(max_queue_, queue_.size());
      cv_.notify_all();
    }
    const double cpu = ThreadCpuSeconds(pthread_self());
    std::lock_guard<std::mutex> lock(mu_);
    final_cpu_s_ = cpu;
    done_ = true;
    cv_.notify_all();
  }

  const irmosaic::FlightSimulator& sim_;
  const int first_;
  const int frames_;
  const double rate_hz_;
  const size_t depth_;
  Clock::time_point start_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::deque<std::pair<SimFrame, Clock::time_point>> queue_;
  size_t max_queue_ = 0;
  bool done_ = false, stop_ = false;
  double final_cpu_s_ = 0.0;
  std::thread thread_;
};

// The q-quantile (0..1) of `values` (nearest rank); 0 when empty.
double Quantile(std::vector<double> values, double q) {
  if (values.empty()) return 0.0;
  std::sort(values.begin(), values.end());
  const size_t k = static_cast<size_t>(std::lround(q * static_cast<double>(values.size() - 1)));
  return values[std::min(k, values.size() - 1)];
}

struct RunConfig {
  int frames = 2000;
  double rate_hz = 0.0;  // 0: as fast as possible.
  std::string store;
  bool optimize = true;
  bool checkpoints = true;
};

// One Mosaicker run over a simulated flight; returns its figures.
// The slowest frame of each of the `count` publishes that put the slowest frames on disk, each
// traced to its parts: how late the
// pipeline took it, its Push, the wait from the end of its Push to the start of the publish that
// put it on disk (the publish clock, the writer's queue: its slices since the previous publish
// are named), and that publish's own time and work (PublishReport). The publish is the one whose
// end is the frame's arrival plus its latency (the time TileStore::PublishedAt gives).
nlohmann::json SlowestFrames(const std::vector<Clock::time_point>& arrival_of,
                             const std::vector<Clock::time_point>& push_start_of,
                             const std::vector<Clock::time_point>& push_end_of,
                             const std::vector<double>& latency_of,
                             std::vector<irmosaic::PublishReport> reports, size_t count) {
  std::vector<size_t> order;
  for (size_t k = 0; k < latency_of.size(); ++k) {
    if (std::isfinite(latency_of[k])) order.push_back(k);
  }
  std::sort(order.begin(), order.end(),
            [&](size_t a, size_t b) { return latency_of[a] > latency_of[b]; });
  std::sort(reports.begin(), reports.end(),
            [](const auto& a, const auto& b) { return a.finished < b.finished; });
  const auto seconds = [](Clock::duration d) { return std::chrono::duration<double>(d).count(); };
  nlohmann::json out = nlohmann::json::array();
  // The slowest frame of each of the `count` slowest publishes (the frames a stall delays go
  // out together: one line per event).
  std::set<int64_t> publishes_listed;
  for (size_t n = 0; n < order.size() && out.size() < count; ++n) {
    const size_t k = order[n];
    const Clock::time_point published =
        arrival_of[k] +
        std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(latency_of[k]));
    // The report whose end is nearest the frame's publication (equal up to rounding).
    auto it = std::lower_bound(
        reports.begin(), reports.end(), published,
        [](const irmosaic::PublishReport& r, Clock::time_point t) { return r.finished < t; });
    if (it == reports.end() ||
        (it != reports.begin() && published - std::prev(it)->finished < it->finished - published)) {
      if (it != reports.begin()) --it;
    }
    nlohmann::json frame = {{"frame", k},
                            {"latency_s", latency_of[k]},
                            {"intake_s", seconds(push_start_of[k] - arrival_of[k])},
                            {"push_s", seconds(push_end_of[k] - push_start_of[k])}};
    if (it != reports.end() && std::abs(seconds(it->finished - published)) < 1e-3) {
      const irmosaic::PublishReport& r = *it;
      if (!publishes_listed.insert(r.generation).second) continue;
      const Clock::time_point previous_end =
          it == reports.begin() ? r.first_request : std::prev(it)->finished;
      frame["to_publish_start_s"] = seconds(r.started - push_end_of[k]);
      frame["publish"] = {
          {"generation", r.generation},
          {"wall_s", seconds(r.finished - r.started)},
          {"first_request_after_arrival_s", seconds(r.first_request - arrival_of[k])},
          {"last_request_after_arrival_s", seconds(r.last_request - arrival_of[k])},
          {"gap_after_previous_publish_s", seconds(r.started - previous_end)},
          {"refresh_slices", r.refresh_slices},
          {"overview_slices", r.overview_slices},
          {"slices_s", r.slices_ms / 1000.0},
          {"level0_tiles", r.level0_tiles},
          {"refreshed_tiles", r.refreshed_tiles},
          {"overview_update", r.overview_update},
          {"overview_update_early", r.overview_update_early},
          {"overview_update_in_publish", r.overview_update_in_publish},
          {"overview_tiles", r.overview_tiles},
          {"frames_gpkg", r.frames_gpkg},
          {"index_s", r.index_ms / 1000.0},
          {"cpu_s", r.cpu_ms / 1000.0},
          {"run_queue_s", r.run_queue_ms / 1000.0}};
    }
    out.push_back(frame);
  }
  return out;
}

nlohmann::json RunMosaicker(const RunConfig& config) {
  irmosaic::FlightSimulator sim(FlightOptions(config.frames));
  MosaickerOptions options;
  options.store_path = config.store;
  options.mode = irmosaic::TileStoreOptions::Mode::kOverwrite;
  options.ground_height_m = sim.options().ground_height_m;
  options.fusion.optimize = config.optimize;
  if (g_tuning.publish_interval_s >= 0) options.publish_interval_s = g_tuning.publish_interval_s;
  if (g_tuning.overview_interval_s >= 0) {
    options.overview_interval_s = g_tuning.overview_interval_s;
  }
  if (g_tuning.tile_size > 0) options.tile_size = g_tuning.tile_size;
  if (!g_tuning.compression.empty()) options.compression = g_tuning.compression;
  if (g_tuning.max_rerenders_per_solve >= 0) {
    options.fusion.max_rerenders_per_solve = g_tuning.max_rerenders_per_solve;
  }
  if (g_tuning.rerender_threshold_px >= 0) {
    options.fusion.rerender_threshold_px = g_tuning.rerender_threshold_px;
  }
  if (g_tuning.rerender_settled >= 0) {
    options.fusion.rerender_settled_frames = g_tuning.rerender_settled != 0;
  }
  if (g_tuning.settled_rerender_threshold_px >= 0) {
    options.fusion.settled_rerender_threshold_px = g_tuning.settled_rerender_threshold_px;
  }
  if (g_tuning.window_frames > 0) options.fusion.window_frames = g_tuning.window_frames;
  if (g_tuning.short_window_frames >= 0) {
    options.fusion.short_window_frames = g_tuning.short_window_frames;
  }
  if (g_tuning.full_window_every > 0) options.fusion.full_window_every = g_tuning.full_window_every;
  if (g_tuning.solve_iterations > 0) options.fusion.solve_iterations = g_tuning.solve_iterations;
  if (!g_tuning.sparse_library.empty()) options.fusion.sparse_library = g_tuning.sparse_library;
  if (g_tuning.solve_every_frames > 0) {
    options.fusion.solve_every_frames = g_tuning.solve_every_frames;
  }
  if (g_tuning.registration_threads > 0) {
    options.registration_threads = g_tuning.registration_threads;
  }
  if (g_tuning.max_neighbours > 0) options.fusion.max_neighbours = g_tuning.max_neighbours;
  if (g_tuning.lsm_level >= 0) options.registration.fine.lsm_level = g_tuning.lsm_level;
  if (g_tuning.max_pair_sigma_px > 0.0) {
    options.registration.fine.max_joint_sigma_px = g_tuning.max_pair_sigma_px;
  }
  if (g_tuning.max_coarse_pair_sigma_px > 0.0) {
    options.registration.fine.max_coarse_joint_sigma_px = g_tuning.max_coarse_pair_sigma_px;
  }
  if (g_tuning.wide_radius_px >= 0.0) options.wide_search_radius_px = g_tuning.wide_radius_px;
  if (g_tuning.keypoints_at_lsm_level >= 0) {
    options.registration.fine.keypoints_at_lsm_level = g_tuning.keypoints_at_lsm_level != 0;
  }
  if (g_tuning.optimizer_nice >= 0) options.fusion.optimizer_nice = g_tuning.optimizer_nice;
  if (g_tuning.max_output_backlog_s >= 0.0) {
    options.fusion.max_output_backlog_s = g_tuning.max_output_backlog_s;
  }
  if (g_tuning.writer_nice >= 0) options.writer_nice = g_tuning.writer_nice;
  if (g_tuning.sync_interval_s >= 0.0) options.sync_interval_s = g_tuning.sync_interval_s;
  if (g_tuning.max_cached_tiles > 0) options.max_cached_tiles = g_tuning.max_cached_tiles;
  if (g_tuning.refresh_quiet_publishes >= 0) {
    options.refresh_quiet_publishes = g_tuning.refresh_quiet_publishes;
  }
  if (g_tuning.refresh_slice_tiles >= 0) {
    options.refresh_slice_tiles = g_tuning.refresh_slice_tiles;
  }
  if (g_tuning.images_in_memory >= 0) options.images_in_memory = g_tuning.images_in_memory;
  if (g_tuning.heap_trim_interval_frames >= 0) {
    options.heap_trim_interval_frames = g_tuning.heap_trim_interval_frames;
  }
  if (g_tuning.tune_heap >= 0) options.tune_heap = g_tuning.tune_heap != 0;
  // Where each frame was last painted (the mosaic on disk shows it there; re-renders can be
  // deferred), by frame index from the first one; NaN until painted. Preallocated (72 bytes a
  // frame) so the flight's memory figures do not see it grow.
  std::vector<Eigen::Matrix3d> painted(
      static_cast<size_t>(config.frames),
      Eigen::Matrix3d::Constant(std::numeric_limits<double>::quiet_NaN()));
  std::mutex painted_mu;
  options.on_frame_painted = [&](const irmosaic::FramePlacement& p) {
    const int64_t k = p.index - g_tuning.first_frame;
    if (k < 0 || k >= config.frames) return;
    std::lock_guard<std::mutex> lock(painted_mu);
    painted[static_cast<size_t>(k)] = p.mosaic_from_image;
  };
  // Publish latencies as the frames reach the disk (Push's thread), for each tenth's quantiles.
  std::vector<double> published_latency_s;
  published_latency_s.reserve(static_cast<size_t>(config.frames));  // Memory figures flat.
  size_t segment_latency_begin = 0;
  // Each frame's arrival, the start and end of its Push, and its publish latency, by frame
  // index from the first one (preallocated, as `painted`), and the store's report of each
  // publish (writer thread): the slowest frames' latencies traced to their parts at the end.
  const size_t n_frames = static_cast<size_t>(config.frames);
  std::vector<Clock::time_point> arrival_of(n_frames), push_start_of(n_frames),
      push_end_of(n_frames);
  std::vector<double> latency_of(n_frames, std::numeric_limits<double>::quiet_NaN());
  std::vector<irmosaic::PublishReport> publish_reports;
  publish_reports.reserve(n_frames / 4 + 64);
  std::mutex reports_mu;
  options.on_frame_published = [&](int64_t index, double latency_s) {
    published_latency_s.push_back(latency_s);
    const int64_t k = index - g_tuning.first_frame;
    if (k >= 0 && k < config.frames) latency_of[static_cast<size_t>(k)] = latency_s;
  };
  options.on_publish = [&](const irmosaic::PublishReport& report) {
    std::lock_guard<std::mutex> lock(reports_mu);
    publish_reports.push_back(report);
  };
  if (std::filesystem::remove_all(config.store) > 0) {
    // A store of the last run just deleted makes this one's files dearer to create: on ext4
    // without a journal (this machine's disk) a new file skips the inodes freed in the last
    // seconds, checked one by one, and a store frees thousands. The writer's kernel time, 1500
    // paced frames: 3.5 ms per frame on a quiet disk, 7.4-7.9 right after deleting such a
    // store, 6.4 after a sync and 6 s, 4.4 after a sync and 60 s (docs/benchmarks.md,
    // "Session 39").
    std::cerr << "flight_bench: removed the previous store " << config.store
              << "; syncing and waiting 60 s so that its freed inodes do not slow this run\n";
    sync();
    std::this_thread::sleep_for(std::chrono::seconds(60));
  }
  irmosaic::Placements truth;
  truth.origin_lat_deg = sim.frame().origin_lat_deg();
  truth.origin_lon_deg = sim.frame().origin_lon_deg();
  truth.gsd_m = sim.grid().gsd_m;
  truth.image_width = sim.camera().width;
  truth.image_height = sim.camera().height;
  ResetPeakRss();
  const double rss_start = StatusMiB("VmRSS");
  const double cpu0 = ProcessCpuSeconds();
  nlohmann::json checkpoints = nlohmann::json::array();
  std::vector<int> marks;  // Every 10 % of the flight.
  for (int k = 1; k <= 10; ++k) marks.push_back(std::max(1, config.frames * k / 10));
  size_t next_mark = 0;
  int64_t placed = 0, pushed = 0;
  double last_wall = 0.0, last_cpu = 0.0, producer_cpu = 0.0, push_wall_s = 0.0;
  std::vector<double> intake_lag_s;
  double push_cpu_s = 0.0;  // The caller's thread inside Push (registration, render, paint).
  double last_push_cpu = 0.0, last_writer_cpu_ms = 0.0, last_writer_system_ms = 0.0,
         last_index_ms = 0.0, last_paint_wait_ms = 0.0;
  int64_t last_tiles_written = 0;
  int last_frames = 0;
  Clock::time_point start;
  {
    Mosaicker mosaicker(options, sim.camera(), sim.MeasuredPos());
    Producer producer(sim, g_tuning.first_frame, config.frames, config.rate_hz, 4);
    start = producer.start();
    SimFrame frame;
    Clock::time_point arrival;
    while (producer.Next(&frame, &arrival)) {
      const auto t0 = Clock::now();
      // How late the pipeline takes the frame (paced: 0 while the caller keeps up).
      intake_lag_s.push_back(std::chrono::duration<double>(t0 - arrival).count());
      truth.frames.push_back({frame.index, frame.time_s, frame.true_mosaic_from_image});
      const double push_cpu0 = ThreadCpuSeconds(pthread_self());
      const irmosaic::PushResult r =
          mosaicker.Push(frame.index, frame.time_s, frame.image, arrival);
      push_cpu_s += ThreadCpuSeconds(pthread_self()) - push_cpu0;
      if (const int64_t k = frame.index - g_tuning.first_frame; k >= 0 && k < config.frames) {
        arrival_of[static_cast<size_t>(k)] = arrival;
        push_start_of[static_cast<size_t>(k)] = t0;
        push_end_of[static_cast<size_t>(k)] = Clock::now();
      }
      push_wall_s += Since(t0);
      ++pushed;
      if (r.placed()) ++placed;
      if (config.checkpoints && next_mark < marks.size() && pushed == marks[next_mark]) {
        if (!g_tuning.malloc_info_dir.empty()) {
          const std::string path =
              g_tuning.malloc_info_dir + "/malloc_info_" + std::to_string(pushed) + ".xml";
          if (FILE* out = std::fopen(path.c_str(), "w")) {
            malloc_info(0, out);
            std::fclose(out);
          } else {
            std::cerr << "flight_bench: cannot write " << path << "\n";
          }
        }
        const double wall = Since(start);
        const double cpu = ProcessCpuSeconds() - cpu0 - producer.cpu_s();
        // Per thread, so that a cost growing with the flight shows where it grows: the
        // foreground's Push (registration, render, paint: nothing in it grows with the flight)
        // against the writer's and its index (VRTs, manifest.json: they grow with the blocks
        // of tiles the store holds). A drift of the machine moves all alike. Push and the writer
        // are CPU time; the index is the writer's wall time in it (TileStore::Stats).
        const irmosaic::TileStore::Stats store_now = mosaicker.store()->stats();
        const double frames_in_segment = std::max<double>(1.0, pushed - last_frames);
        // Frames published since the last checkpoint (those of the tenth, less the last ones
        // still in flight, plus the previous tenth's last ones).
        const std::vector<double> segment_latency(
            published_latency_s.begin() + static_cast<std::ptrdiff_t>(segment_latency_begin),
            published_latency_s.end());
        segment_latency_begin = published_latency_s.size();
        checkpoints.push_back(
            {{"percent", 100.0 * static_cast<double>(pushed) / config.frames},
             {"frames", pushed},
             {"wall_s", wall},
             {"segment_frames_per_s", (pushed - last_frames) / std::max(1e-9, wall - last_wall)},
             {"segment_cpu_ms_per_frame", 1000.0 * (cpu - last_cpu) / frames_in_segment},
             {"segment_push_cpu_ms_per_frame",
              1000.0 * (push_cpu_s - last_push_cpu) / frames_in_segment},
             {"segment_writer_cpu_ms_per_frame",
              (store_now.writer_cpu_ms - last_writer_cpu_ms) / frames_in_segment},
             {"segment_writer_system_cpu_ms_per_frame",
              (store_now.writer_system_cpu_ms - last_writer_system_ms) / frames_in_segment},
             {"segment_index_ms_per_frame",
              (store_now.index_ms_total - last_index_ms) / frames_in_segment},
             {"segment_frames_published", segment_latency.size()},
             {"segment_publish_latency_p50_s", Quantile(segment_latency, 0.50)},
             {"segment_publish_latency_p99_s", Quantile(segment_latency, 0.99)},
             {"segment_publish_latency_max_s", Quantile(segment_latency, 1.0)},
             // The caller's Paint waiting for the writer (the store's back-pressure).
             {"segment_paint_wait_s",
              (store_now.paint_wait_ms_total - last_paint_wait_ms) / 1000.0},
             {"segment_tiles_written_per_frame",
              static_cast<double>(store_now.tiles_written - last_tiles_written) /
                  frames_in_segment},
             {"rss_mib", StatusMiB("VmRSS")},
             {"peak_rss_mib", StatusMiB("VmHWM")},
             {"optimizer_lag_frames", mosaicker.summary().fusion.optimizer_lag_frames},
             {"held_images", mosaicker.summary().fusion.held_images},
             // glibc's heap, all arenas: bytes in live allocations (small + mmapped) and
             // free bytes the heap keeps (fragmentation, or ready for reuse).
             {"heap_in_use_mib", HeapMiB(true)},
             {"heap_free_mib", HeapMiB(false)},
             {"simulator_cache_mib", static_cast<double>(sim.ground().cached_bytes()) / 1048576.0},
             {"held_image_mib",
              static_cast<double>(mosaicker.summary().fusion.held_image_bytes) / 1048576.0}});
        const auto& c = checkpoints.back();
        std::cerr << "flight_bench: " << pushed << "/" << config.frames << " frames, "
                  << c["segment_frames_per_s"].get<double>() << " frames/s, "
                  << c["segment_cpu_ms_per_frame"].get<double>() << " CPU ms/frame (Push "
                  << c["segment_push_cpu_ms_per_frame"].get<double>() << ", writer "
                  << c["segment_writer_cpu_ms_per_frame"].get<double>() << " (kernel "
                  << c["segment_writer_system_cpu_ms_per_frame"].get<double>() << "), index (wall) "
                  << c["segment_index_ms_per_frame"].get<double>() << "; tiles written "
                  << c["segment_tiles_written_per_frame"].get<double>()
                  << "/frame), publish latency p50 / p99 / max "
                  << c["segment_publish_latency_p50_s"].get<double>() << " / "
                  << c["segment_publish_latency_p99_s"].get<double>() << " / "
                  << c["segment_publish_latency_max_s"].get<double>() << " s, RSS "
                  << c["rss_mib"].get<double>() << " MiB (peak " << c["peak_rss_mib"].get<double>()
                  << "), images held " << c["held_images"].get<int64_t>() << " ("
                  << c["held_image_mib"].get<double>() << " MiB), simulator's ground cache "
                  << c["simulator_cache_mib"].get<double>() << " MiB, heap in use "
                  << c["heap_in_use_mib"].get<double>() << " MiB, heap free "
                  << c["heap_free_mib"].get<double>() << " MiB" << std::endl;
        last_wall = wall;
        last_cpu = cpu;
        last_push_cpu = push_cpu_s;
        last_writer_cpu_ms = store_now.writer_cpu_ms;
        last_writer_system_ms = store_now.writer_system_cpu_ms;
        last_index_ms = store_now.index_ms_total;
        last_paint_wait_ms = store_now.paint_wait_ms_total;
        last_tiles_written = store_now.tiles_written;
        last_frames = static_cast<int>(pushed);
        ++next_mark;
      }
    }
    const double foreground_s = Since(start);
    producer_cpu = producer.cpu_s();
    if (g_tuning.exit_before_finish) {
      std::cerr << "flight_bench: leaving before Finish() (--exit-before-finish)" << std::endl;
      std::_Exit(0);
    }
    const auto finish0 = Clock::now();
    mosaicker.Finish();
    const double finish_s = Since(finish0);
    const double wall = Since(start);
    const double cpu = ProcessCpuSeconds() - cpu0 - producer_cpu;
    const irmosaic::MosaickerSummary s = mosaicker.summary();
    const irmosaic::TileStore::Stats st = mosaicker.store()->stats();
    // Final placements against the truth (truth mosaic pixels).
    irmosaic::Placements run;
    run.origin_lat_deg = s.origin_lat_deg;
    run.origin_lon_deg = s.origin_lon_deg;
    run.gsd_m = s.gsd_m;
    int64_t oldest_neighbour = 0;  // Frames between a frame and its oldest neighbour.
    // What the worst placements were (a far-off frame in a long run is found by its index).
    struct Facts {
      bool pos_only = false;
      size_t neighbours = 0;
      int inliers = 0;
      int optimized_times = 0;
      std::string note;
    };
    std::map<int64_t, Facts> facts;
    for (const irmosaic::FramePlacement& p : mosaicker.Placements()) {
      run.frames.push_back({static_cast<int>(p.index), p.time_s, p.mosaic_from_image});
      for (int64_t n : p.neighbours) oldest_neighbour = std::max(oldest_neighbour, p.index - n);
      facts[p.index] = {p.pos_only, p.neighbours.size(), p.inliers, p.optimized_times, p.note};
    }
    const irmosaic::PlacementScore score =
        irmosaic::Evaluator(truth).ScorePlacements(run, "flight_bench");
    // The mosaic as painted (what a reader of the store sees) against the truth, and against
    // the final placements (what the disk lags behind the solution).
    irmosaic::Placements on_disk = run;
    on_disk.frames.clear();
    {
      std::lock_guard<std::mutex> lock(painted_mu);
      for (const irmosaic::Placement& f : run.frames) {
        const Eigen::Matrix3d& h = painted[static_cast<size_t>(f.index - g_tuning.first_frame)];
        if (std::isfinite(h(2, 2))) on_disk.frames.push_back({f.index, f.time_s, h});
      }
    }
    const irmosaic::PlacementScore disk_score =
        irmosaic::Evaluator(truth).ScorePlacements(on_disk, "flight_bench (as painted)");
    irmosaic::Placements solution = run;
    solution.image_width = truth.image_width;
    solution.image_height = truth.image_height;
    const irmosaic::PlacementScore disk_lag =
        irmosaic::Evaluator(solution).ScorePlacements(on_disk, "flight_bench (painted - final)");
    int64_t disk_lag_over_1px = 0;
    for (const irmosaic::FrameScore& f : disk_lag.frames) disk_lag_over_1px += f.rmse_px > 1.0;
    const std::vector<irmosaic::FrameScore> worst = irmosaic::WorstFrames(score, 5);
    int64_t over_5px = 0, over_20px = 0;
    for (const irmosaic::FrameScore& f : score.frames) {
      over_5px += f.rmse_px > 5.0;
      over_20px += f.rmse_px > 20.0;
    }
    // By the frame's position in its sweep (0: the sweep's first frame; frames of a sweep
    // differ in obliquity, footprint and neighbours): where the error sits.
    const int per_sweep = std::max(1, sim.options().frames_per_sweep);
    std::vector<std::vector<double>> by_position(static_cast<size_t>(per_sweep));
    for (const irmosaic::FrameScore& f : score.frames) {
      by_position[static_cast<size_t>(f.index % per_sweep)].push_back(f.rmse_px);
    }
    nlohmann::json by_position_json = nlohmann::json::array();
    for (int k = 0; k < per_sweep; ++k) {
      const irmosaic::ErrorStats e =
          irmosaic::ComputeErrorStats(by_position[static_cast<size_t>(k)]);
      by_position_json.push_back({{"position", k},
                                  {"frames", e.count},
                                  {"mean_px", e.mean},
                                  {"p95_px", e.p95},
                                  {"max_px", e.max}});
    }
    nlohmann::json worst_json = nlohmann::json::array();
    for (const irmosaic::FrameScore& f : worst) {
      const Facts& x = facts[f.index];
      worst_json.push_back({{"index", f.index},
                            {"rmse_px", f.rmse_px},
                            {"pos_only", x.pos_only},
                            {"neighbours", x.neighbours},
                            {"inliers", x.inliers},
                            {"optimized_times", x.optimized_times},
                            {"note", x.note}});
    }
    const nlohmann::json slowest =
        SlowestFrames(arrival_of, push_start_of, push_end_of, latency_of, publish_reports, 8);
    int64_t store_bytes = 0;
    for (const auto& e : std::filesystem::recursive_directory_iterator(config.store)) {
      if (e.is_regular_file()) store_bytes += static_cast<int64_t>(e.file_size());
    }
    return {{"frames", config.frames},
            {"rate_hz", config.rate_hz},
            {"optimize", config.optimize},
            {"frames_placed", placed},
            {"frames_registered", s.frames_registered},
            {"frames_pos_only", s.frames_pos_only},
            {"wall_s", wall},
            {"foreground_wall_s", foreground_s},
            {"finish_s", finish_s},
            {"frames_per_s", config.frames / wall},
            {"foreground_frames_per_s", config.frames / foreground_s},
            {"push_ms_per_frame", 1000.0 * push_wall_s / config.frames},
            {"intake_lag_p50_s", Quantile(intake_lag_s, 0.50)},
            {"intake_lag_p99_s", Quantile(intake_lag_s, 0.99)},
            {"intake_lag_max_s", Quantile(intake_lag_s, 1.0)},
            {"push_cpu_ms_per_frame", 1000.0 * push_cpu_s / config.frames},
            {"pipeline_cpu_s", cpu},
            {"pipeline_cpu_ms_per_frame", 1000.0 * cpu / config.frames},
            {"renderer_cpu_ms_per_frame", 1000.0 * producer_cpu / config.frames},
            {"publish_latency_p50_s", s.publish_latency_p50_s},
            {"publish_latency_p99_s", s.publish_latency_p99_s},
            {"publish_latency_max_s", s.publish_latency_max_s},
            {"generations_published", s.generations_published},
            {"writer_busy_ms_per_frame", st.writer_busy_ms / config.frames},
            {"writer_cpu_ms_per_frame", st.writer_cpu_ms / config.frames},
            {"writer_system_cpu_ms_per_frame", st.writer_system_cpu_ms / config.frames},
            {"paint_ms_per_frame", st.paint_ms_total / config.frames},
            {"paint_waits", st.paint_waits},
            {"paint_wait_s", st.paint_wait_ms_total / 1000.0},
            {"tiles_written", st.tiles_written},
            {"overview_tiles_written", st.overview_tiles_written},
            {"blocks_copied", st.blocks_copied},
            {"blocks_encoded", st.blocks_encoded},
            {"publishes", st.publishes},
            {"overview_updates", st.overview_updates},
            {"overview_updates_early", st.overview_updates_early},
            {"overview_updates_in_publish", st.overview_updates_in_publish},
            {"overview_slices", st.overview_slices},
            {"refresh_slices", st.refresh_slices},
            {"refresh_tiles_written", st.refresh_tiles_written},
            {"tile_reloads", st.tile_reloads},
            {"overview_reads", st.overview_reads},
            {"tile_copies", st.tile_copies},
            {"store_bytes_per_frame", static_cast<double>(store_bytes) / config.frames},
            {"optimizer_solves", s.fusion.solves},
            {"optimizer_full_solves", s.fusion.full_solves},
            {"optimizer_mean_solve_ms",
             s.fusion.solves ? s.fusion.total_solve_ms / s.fusion.solves : 0.0},
            {"optimizer_max_solve_ms", s.fusion.max_solve_ms},
            {"optimizer_mean_solve_cpu_ms",
             s.fusion.solves ? s.fusion.total_solve_cpu_ms / s.fusion.solves : 0.0},
            {"optimizer_cpu_ms_per_frame", s.fusion.total_solve_cpu_ms / config.frames},
            {"rerendered_frames", s.fusion.rerendered_frames},
            {"rerendered_ahead", s.fusion.rerendered_ahead},
            {"deferred_rerenders", s.fusion.deferred_rerenders},
            {"radiometric_rerenders", s.fusion.radiometric_rerenders},
            {"rerender_candidates", s.fusion.rerender_candidates},
            {"settled_rerender_candidates", s.fusion.settled_rerender_candidates},
            {"settled_rerenders", s.fusion.settled_rerenders},
            {"settled_rerenders_on_leaving", s.fusion.settled_rerenders_on_leaving},
            {"settled_left_lagging", s.fusion.settled_left_lagging},
            {"oldest_neighbour_frames", oldest_neighbour},
            {"held_images", s.fusion.held_images},
            {"held_image_mib", static_cast<double>(s.fusion.held_image_bytes) / 1048576.0},
            {"images_in_memory", options.images_in_memory},
            {"spilled_images", s.fusion.spilled_images},
            {"spill_file_mib", static_cast<double>(s.fusion.spill_file_bytes) / 1048576.0},
            {"spill_reads", s.fusion.spill_reads},
            {"spill_error", s.fusion.spill_error},
            {"rss_start_mib", rss_start},
            {"placement_mean_px", score.rmse_px.mean},
            {"placement_p95_px", score.rmse_px.p95},
            {"placement_max_px", score.rmse_px.max},
            {"placement_frames_over_5px", over_5px},
            {"placement_frames_over_20px", over_20px},
            {"placement_worst_frames", worst_json},
            {"placement_by_sweep_position", by_position_json},
            {"painted_frames", disk_score.frames_scored},
            {"painted_mean_px", disk_score.rmse_px.mean},
            {"painted_p95_px", disk_score.rmse_px.p95},
            {"painted_max_px", disk_score.rmse_px.max},
            {"painted_lag_mean_px", disk_lag.rmse_px.mean},
            {"painted_lag_p95_px", disk_lag.rmse_px.p95},
            {"painted_lag_max_px", disk_lag.rmse_px.max},
            {"painted_lag_frames_over_1px", disk_lag_over_1px},
            {"publish_interval_s", options.publish_interval_s},
            {"overview_interval_s", options.overview_interval_s},
            {"tile_size", options.tile_size},
            {"compression", options.compression},
            {"max_rerenders_per_solve", options.fusion.max_rerenders_per_solve},
            {"rerender_threshold_px", options.fusion.rerender_threshold_px},
            {"settled_rerender_threshold_px", options.fusion.settled_rerender_threshold_px},
            {"rerender_settled_frames", options.fusion.rerender_settled_frames},
            {"mean_seam_lag_px", s.fusion.mean_seam_lag_px},
            {"mean_painted_lag_px", s.fusion.mean_painted_lag_px},
            {"window_frames", options.fusion.window_frames},
            {"solve_every_frames", options.fusion.solve_every_frames},
            {"short_window_frames", options.fusion.short_window_frames},
            {"full_window_every", options.fusion.full_window_every},
            {"solve_iterations", options.fusion.solve_iterations},
            {"registration_threads", options.registration_threads},
            {"heap_trim_interval_frames", options.heap_trim_interval_frames},
            {"tune_heap", options.tune_heap},
            {"max_cached_tiles", options.max_cached_tiles},
            {"refresh_slice_tiles", options.refresh_slice_tiles},
            {"refresh_quiet_publishes", options.refresh_quiet_publishes},
            {"simulator_cache_mb_bound", sim.options().ground_cache_mb},
            {"peak_rss_mib", StatusMiB("VmHWM")},
            {"slowest_frames", slowest},
            {"checkpoints", checkpoints}};
  }
}

// Frames as 8-bit images for the OpenCV baselines (a linear stretch of the 16-bit signal).
std::vector<cv::Mat> EightBitFrames(int frames) {
  irmosaic::FlightSimulator sim(FlightOptions(frames));
  std::vector<cv::Mat> out;
  for (int i = 0; i < frames; ++i) {
    cv::Mat image = sim.Render(i).image, eight;
    double lo = 0, hi = 0;
    cv::minMaxLoc(image, &lo, &hi);
    image.convertTo(eight, CV_8U, 255.0 / std::max(1.0, hi - lo),
                    -lo * 255.0 / std::max(1.0, hi - lo));
    out.push_back(eight);
  }
  return out;
}

nlohmann::json RunStitcher(int frames) {
  std::vector<cv::Mat> images = EightBitFrames(frames);
  // The Stitcher's seam finder takes three channels only.
  for (cv::Mat& image : images) cv::cvtColor(image, image, cv::COLOR_GRAY2BGR);
  const auto start = Clock::now();
  cv::Ptr<cv::Stitcher> stitcher = cv::Stitcher::create(cv::Stitcher::SCANS);
  cv::Mat pano;
  const cv::Stitcher::Status status = stitcher->stitch(images, pano);
  const double seconds = Since(start);
  const char* names[] = {"OK", "ERR_NEED_MORE_IMGS", "ERR_HOMOGRAPHY_EST_FAIL",
                         "ERR_CAMERA_PARAMS_ADJUST_FAIL"};
  return {{"method", "cv::Stitcher SCANS"},
          {"frames", frames},
          {"seconds", seconds},
          // Success: every frame in the panorama (the Stitcher drops frames it cannot match).
          {"success",
           status == cv::Stitcher::OK && static_cast<int>(stitcher->component().size()) == frames},
          {"status", names[static_cast<int>(status)]},
          {"frames_in_result", stitcher->component().size()},
          {"output_px", static_cast<double>(pano.total())}};
}

// A plain incremental pipeline: ORB on each frame, brute-force Hamming matches to the previous
// frame with a ratio test, RANSAC homography, chained onto the first frame; frames composited
// onto a canvas. No POS, no global adjustment: what a quick implementation does.
nlohmann::json RunOrb(int frames) {
  std::vector<cv::Mat> images = EightBitFrames(frames);
  const auto start = Clock::now();
  cv::Ptr<cv::ORB> orb = cv::ORB::create(1500);
  cv::BFMatcher matcher(cv::NORM_HAMMING);
  std::vector<cv::KeyPoint> prev_kp;
  cv::Mat prev_desc;
  std::vector<cv::Mat> chain(images.size());
  int failed = 0;
  for (size_t i = 0; i < images.size(); ++i) {
    std::vector<cv::KeyPoint> kp;
    cv::Mat desc;
    orb->detectAndCompute(images[i], cv::noArray(), kp, desc);
    chain[i] = cv::Mat::eye(3, 3, CV_64F);
    if (i > 0) {
      std::vector<std::vector<cv::DMatch>> knn;
      if (!desc.empty() && !prev_desc.empty()) matcher.knnMatch(desc, prev_desc, knn, 2);
      std::vector<cv::Point2f> from, to;
      for (const auto& m : knn) {
        if (m.size() == 2 && m[0].distance < 0.75f * m[1].distance) {
          from.push_back(kp[m[0].queryIdx].pt);
          to.push_back(prev_kp[m[0].trainIdx].pt);
        }
      }
      cv::Mat h;
      cv::Mat inliers;
      if (from.size() >= 8) h = cv::findHomography(from, to, cv::RANSAC, 3.0, inliers);
      if (h.empty() || cv::countNonZero(inliers) < 12) {
        ++failed;
        h = cv::Mat::eye(3, 3, CV_64F);  // Lost: assume no motion.
      }
      chain[i] = chain[i - 1] * h;
    }
    prev_kp = std::move(kp);
    prev_desc = desc;
  }
  const double register_s = Since(start);
  // Composite: bounding box of the chained footprints, capped at 400 Mpx (else "failed").
  double min_x = 0, min_y = 0, max_x = 0, max_y = 0;
  for (size_t i = 0; i < images.size(); ++i) {
    std::vector<cv::Point2f> corners = {{0, 0},
                                        {static_cast<float>(images[i].cols), 0},
                                        {static_cast<float>(images[i].cols),
                                         static_cast<float>(images[i].rows)},
                                        {0, static_cast<float>(images[i].rows)}},
                             mapped;
    cv::perspectiveTransform(corners, mapped, chain[i]);
    for (const auto& p : mapped) {
      min_x = std::min<double>(min_x, p.x);
      min_y = std::min<double>(min_y, p.y);
      max_x = std::max<double>(max_x, p.x);
      max_y = std::max<double>(max_y, p.y);
    }
  }
  const double width = max_x - min_x, height = max_y - min_y;
  const bool fits = std::isfinite(width * height) && width * height < 4e8;
  if (fits) {
    cv::Mat canvas(static_cast<int>(height) + 1, static_cast<int>(width) + 1, CV_8U, cv::Scalar(0));
    const cv::Mat shift = (cv::Mat_<double>(3, 3) << 1, 0, -min_x, 0, 1, -min_y, 0, 0, 1);
    cv::Mat full_mask(images[0].size(), CV_8U, cv::Scalar(255));
    for (size_t i = 0; i < images.size(); ++i) {
      cv::Mat warped, mask;
      cv::warpPerspective(images[i], warped, shift * chain[i], canvas.size());
      cv::warpPerspective(full_mask, mask, shift * chain[i], canvas.size(), cv::INTER_NEAREST);
      warped.copyTo(canvas, mask);
    }
  }
  const double seconds = Since(start);
  return {{"method", "ORB+RANSAC incremental"},
          {"frames", frames},
          {"seconds", seconds},
          {"register_seconds", register_s},
          {"success", fits && failed == 0},
          {"pairs_failed", failed},
          {"canvas_mpx", width * height / 1e6}};
}

// Runs this program with --child KIND in its own process: its peak memory is its own.
nlohmann::json RunChild(const std::string& self, const std::string& kind, int frames,
                        double timeout_s, const std::string& store_root) {
  const std::string json_path =
      store_root + "/child_" + kind + "_" + std::to_string(frames) + ".json";
  std::filesystem::remove(json_path);
  std::vector<std::string> args = {self,
                                   "--child",
                                   kind,
                                   "--frames",
                                   std::to_string(frames),
                                   "--json",
                                   json_path,
                                   "--store",
                                   store_root + "/child_store",
                                   "--mmap-threshold",
                                   std::to_string(g_tuning.mmap_threshold),
                                   "--heap-tuning",
                                   std::to_string(g_tuning.tune_heap),
                                   "--cv-threads",
                                   std::to_string(g_tuning.cv_threads),
                                   "--seed",
                                   std::to_string(g_tuning.seed),
                                   "--bit-depth",
                                   std::to_string(g_tuning.bit_depth),
                                   "--first",
                                   std::to_string(g_tuning.first_frame)};
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  pid_t pid = 0;
  const auto start = Clock::now();
  if (posix_spawn(&pid, self.c_str(), nullptr, nullptr, argv.data(), environ) != 0) {
    return {{"method", kind}, {"frames", frames}, {"success", false}, {"status", "spawn failed"}};
  }
  int status = 0;
  rusage usage{};
  bool timed_out = false;
  while (true) {
    const pid_t r = wait4(pid, &status, WNOHANG, &usage);
    if (r == pid) break;
    if (Since(start) > timeout_s) {
      kill(pid, SIGKILL);
      wait4(pid, &status, 0, &usage);
      timed_out = true;
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  nlohmann::json result;
  std::ifstream in(json_path);
  if (!timed_out && in) {
    result = nlohmann::json::parse(in, nullptr, false);
  }
  if (!result.is_object()) {
    result = {
        {"method", kind},
        {"frames", frames},
        {"success", false},
        {"status", timed_out ? "timeout after " + std::to_string(static_cast<int>(timeout_s)) + " s"
                             : "crashed (exit status " + std::to_string(status) + ")"},
        {"seconds", Since(start)}};
  }
  result["peak_rss_mib"] = result.contains("own_peak_rss_mib")
                               ? result["own_peak_rss_mib"].get<double>()
                               : static_cast<double>(usage.ru_maxrss) / 1024.0;
  result["cpu_s"] = Seconds({usage.ru_utime.tv_sec, usage.ru_utime.tv_usec * 1000}) +
                    Seconds({usage.ru_stime.tv_sec, usage.ru_stime.tv_usec * 1000});
  return result;
}

std::string Fixed(double v, int digits) {
  std::ostringstream s;
  s << std::fixed << std::setprecision(digits) << v;
  return s.str();
}

// The slowest frames' latencies by part (SlowestFrames), one line each.
void PrintSlowestFrames(const nlohmann::json& slowest) {
  if (slowest.empty()) return;
  std::cout << "slowest frames: latency = taken late + Push + to the publish's start + publish "
               "(s); the publish's work; the writer's slices before it\n";
  for (const auto& f : slowest) {
    std::cout << "  frame " << f["frame"].get<int64_t>() << ": " << Fixed(f["latency_s"], 3)
              << " = " << Fixed(f["intake_s"], 3) << " + " << Fixed(f["push_s"], 3);
    if (!f.contains("publish")) {
      std::cout << " + (its publish not reported)\n";
      continue;
    }
    const auto& r = f["publish"];
    std::cout << " + " << Fixed(f["to_publish_start_s"], 3) << " + " << Fixed(r["wall_s"], 3)
              << "; " << r["level0_tiles"].get<int>() << " level-0 tiles ("
              << r["refreshed_tiles"].get<int>() << " refreshed)";
    if (r["overview_update_in_publish"].get<bool>()) {
      std::cout << ", overview update inside (" << r["overview_tiles"].get<int>() << " tiles)";
    } else if (r["overview_update"].get<bool>()) {
      std::cout << ", overview update started"
                << (r["overview_update_early"].get<bool>() ? " early" : "");
    }
    if (r["frames_gpkg"].get<bool>()) std::cout << ", frames.gpkg";
    std::cout << ", index " << Fixed(r["index_s"], 3) << " s, CPU " << Fixed(r["cpu_s"], 3)
              << " s, waiting for a CPU " << Fixed(r["run_queue_s"], 3) << " s; requests "
              << Fixed(r["first_request_after_arrival_s"], 3) << " .. "
              << Fixed(r["last_request_after_arrival_s"], 3) << " s after arrival; "
              << r["refresh_slices"].get<int>() << " refresh + " << r["overview_slices"].get<int>()
              << " overview slices (" << Fixed(r["slices_s"], 3) << " s) in the "
              << Fixed(r["gap_after_previous_publish_s"], 3) << " s since the previous publish\n";
  }
}

std::string MachineLine() {
  std::string model = "unknown CPU";
  std::ifstream cpu("/proc/cpuinfo");
  std::string line;
  while (std::getline(cpu, line)) {
    if (line.rfind("model name", 0) == 0) {
      model = line.substr(line.find(':') + 2);
      break;
    }
  }
  double load = 0.0;
  std::ifstream("/proc/loadavg") >> load;
  return model + ", " + std::to_string(std::thread::hardware_concurrency()) +
         " cores, load average " + Fixed(load, 2) + " at start";
}

}  // namespace

int main(int argc, char** argv) {
  int frames = 2000, paced_frames = 750;
  std::vector<int> compare = {100, 300};
  bool optimize = true;
  double timeout_s = 900.0;
  std::string json_path, store = "/tmp/flight_bench", child;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::cerr << "flight_bench: " << a << " needs a value\n";
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--frames") {
      frames = std::stoi(value());
    } else if (a == "--paced-frames") {
      paced_frames = std::stoi(value());
    } else if (a == "--compare") {
      compare.clear();
      std::stringstream list(value());
      std::string item;
      while (std::getline(list, item, ',')) compare.push_back(std::stoi(item));
    } else if (a == "--no-compare") {
      compare.clear();
    } else if (a == "--no-optimize") {
      optimize = false;
    } else if (a == "--timeout") {
      timeout_s = std::stod(value());
    } else if (a == "--json") {
      json_path = value();
    } else if (a == "--store") {
      store = value();
    } else if (a == "--publish-interval") {
      g_tuning.publish_interval_s = std::stod(value());
    } else if (a == "--overview-interval") {
      g_tuning.overview_interval_s = std::stod(value());
    } else if (a == "--tile-size") {
      g_tuning.tile_size = std::stoi(value());
    } else if (a == "--compression") {
      g_tuning.compression = value();
    } else if (a == "--max-rerenders") {
      g_tuning.max_rerenders_per_solve = std::stoi(value());
    } else if (a == "--rerender-threshold") {
      g_tuning.rerender_threshold_px = std::stod(value());
    } else if (a == "--settled-rerender-threshold") {
      g_tuning.settled_rerender_threshold_px = std::stod(value());
    } else if (a == "--settled-rerenders") {
      g_tuning.rerender_settled = 1;
    } else if (a == "--window") {
      g_tuning.window_frames = std::stoi(value());
    } else if (a == "--short-window") {
      g_tuning.short_window_frames = std::stoi(value());
    } else if (a == "--full-every") {
      g_tuning.full_window_every = std::stoi(value());
    } else if (a == "--solve-iterations") {
      g_tuning.solve_iterations = std::stoi(value());
    } else if (a == "--sparse-library") {
      g_tuning.sparse_library = value();
    } else if (a == "--solve-every") {
      g_tuning.solve_every_frames = std::stoi(value());
    } else if (a == "--registration-threads") {
      g_tuning.registration_threads = std::stoi(value());
    } else if (a == "--max-neighbours") {
      g_tuning.max_neighbours = std::stoi(value());
    } else if (a == "--optimizer-nice") {
      g_tuning.optimizer_nice = std::stoi(value());
    } else if (a == "--max-output-backlog") {
      g_tuning.max_output_backlog_s = std::stod(value());
    } else if (a == "--writer-nice") {
      g_tuning.writer_nice = std::stoi(value());
    } else if (a == "--sync-interval") {
      g_tuning.sync_interval_s = std::stod(value());
    } else if (a == "--lsm-level") {
      g_tuning.lsm_level = std::stoi(value());
    } else if (a == "--max-pair-sigma") {
      g_tuning.max_pair_sigma_px = std::stod(value());
    } else if (a == "--max-coarse-pair-sigma") {
      g_tuning.max_coarse_pair_sigma_px = std::stod(value());
    } else if (a == "--wide-radius") {
      g_tuning.wide_radius_px = std::stod(value());
    } else if (a == "--keypoints-at-level") {
      g_tuning.keypoints_at_lsm_level = std::stoi(value());
    } else if (a == "--heap-tuning") {
      g_tuning.tune_heap = std::stoi(value());
    } else if (a == "--heap-trim-every") {
      g_tuning.heap_trim_interval_frames = std::stoi(value());
    } else if (a == "--max-cached-tiles") {
      g_tuning.max_cached_tiles = std::stoi(value());
    } else if (a == "--refresh-slice-tiles") {
      g_tuning.refresh_slice_tiles = std::stoi(value());
    } else if (a == "--refresh-quiet-publishes") {
      g_tuning.refresh_quiet_publishes = std::stoi(value());
    } else if (a == "--images-in-memory") {
      g_tuning.images_in_memory = std::stoi(value());
    } else if (a == "--ground-cache-mb") {
      g_tuning.ground_cache_mb = std::stoi(value());
    } else if (a == "--mmap-threshold") {
      g_tuning.mmap_threshold = std::stoll(value());
    } else if (a == "--exit-before-finish") {
      g_tuning.exit_before_finish = true;
    } else if (a == "--malloc-info") {
      g_tuning.malloc_info_dir = value();
      std::filesystem::create_directories(g_tuning.malloc_info_dir);
    } else if (a == "--cv-threads") {
      g_tuning.cv_threads = std::stoi(value());
    } else if (a == "--seed") {
      g_tuning.seed = std::stoull(value());
    } else if (a == "--first") {
      g_tuning.first_frame = std::stoi(value());
      if (g_tuning.first_frame < 0) {
        std::cerr << "flight_bench: --first must be 0 or more\n";
        return 2;
      }
    } else if (a == "--bit-depth") {
      g_tuning.bit_depth = std::stoi(value());
      if (g_tuning.bit_depth != 0 && g_tuning.bit_depth != 8 && g_tuning.bit_depth != 16) {
        std::cerr << "flight_bench: --bit-depth must be 8 or 16\n";
        return 2;
      }
    } else if (a == "--child") {
      child = value();
    } else {
      std::cerr
          << "usage: flight_bench [--frames N] [--paced-frames N] [--compare 100,300] "
             "[--no-compare] [--no-optimize] [--store DIR] [--json FILE] [--timeout S] "
             "[--publish-interval S] [--max-rerenders N] [--rerender-threshold PX] "
             "[--settled-rerender-threshold PX] [--settled-rerenders] "
             "[--window N] [--short-window N] [--full-every N] [--solve-every N] "
             "[--solve-iterations N] [--sparse-library SUITE_SPARSE|EIGEN_SPARSE] "
             "[--registration-threads N] [--max-neighbours N] [--lsm-level N] "
             "[--keypoints-at-level 0|1] "
             "[--max-pair-sigma PX] "
             "[--max-coarse-pair-sigma PX] [--wide-radius PX] "
             "[--optimizer-nice N] [--writer-nice N] [--sync-interval S] [--max-output-backlog S] "
             "[--overview-interval S] [--tile-size N] [--compression ZSTD|DEFLATE|LZW|NONE] "
             "[--heap-trim-every N] [--heap-tuning 0|1] [--max-cached-tiles N] "
             "[--refresh-slice-tiles N] [--refresh-quiet-publishes N] "
             "[--images-in-memory N] "
             "[--ground-cache-mb N] "
             "[--mmap-threshold BYTES] "
             "[--cv-threads N] [--seed N] [--first N] [--bit-depth 8|16] "
             "[--malloc-info DIR] "
             "[--exit-before-finish]\n";
      return 2;
    }
  }
  if (g_tuning.cv_threads < 1) {
    std::cerr << "flight_bench: --cv-threads must be at least 1\n";
    return 2;
  }
  cv::setNumThreads(g_tuning.cv_threads);
  // The Mosaicker's processes only (the peers keep glibc's default).
  if (child != "stitcher" && child != "orb" && g_tuning.mmap_threshold > 0 &&
      (g_tuning.mmap_threshold > std::numeric_limits<int>::max() ||
       mallopt(M_MMAP_THRESHOLD, static_cast<int>(g_tuning.mmap_threshold)) != 1)) {
    std::cerr << "flight_bench: glibc refused --mmap-threshold " << g_tuning.mmap_threshold << "\n";
    return 2;
  }

  if (!child.empty()) {
    nlohmann::json result;
    if (child == "stitcher") {
      result = RunStitcher(frames);
    } else if (child == "orb") {
      result = RunOrb(frames);
    } else {
      RunConfig config;
      config.frames = frames;
      config.store = store;
      config.checkpoints = false;
      const nlohmann::json r = RunMosaicker(config);
      result = {{"method", "irmosaic Mosaicker"},
                {"frames", frames},
                {"seconds", r["wall_s"]},
                {"success", r["frames_placed"] == frames},
                {"frames_registered", r["frames_registered"]}};
    }
    // Its own peak (VmHWM after exec); wait4's ru_maxrss starts from the parent's.
    result["own_peak_rss_mib"] = StatusMiB("VmHWM");
    std::ofstream(json_path) << result.dump(2) << "\n";
    return 0;
  }

  std::filesystem::create_directories(store);
  nlohmann::json doc;
  doc["machine"] = MachineLine();
  doc["mmap_threshold"] = g_tuning.mmap_threshold;
  doc["cv_threads"] = g_tuning.cv_threads;
  // How the own warp reads its pixel pairs here (gather instruction or 8 loads, measured once).
  doc["warp_gather"] = irmosaic::warp::GatherPathName();
  doc["seed"] = FlightOptions(1).seed;
  doc["bit_depth"] = FlightOptions(1).sensor.bit_depth;
  std::cout << "flight_bench: " << doc["machine"].get<std::string>() << ", the own warp's gather "
            << doc["warp_gather"].get<std::string>() << "\n";

  if (frames > 0) {
    RunConfig free_run;
    free_run.frames = frames;
    free_run.store = store + "/free";
    free_run.optimize = optimize;
    const nlohmann::json f = RunMosaicker(free_run);
    doc["free"] = f;
    std::cout << "\nAs fast as possible, " << frames << " frames ("
              << (optimize ? "with" : "without") << " the optimizer):\n"
              << std::setw(8) << "% done" << std::setw(9) << "frames" << std::setw(10) << "wall s"
              << std::setw(12) << "frames/s" << std::setw(14) << "CPU ms/frame" << std::setw(8)
              << "Push" << std::setw(8) << "writer" << std::setw(8) << "index*" << std::setw(10)
              << "RSS MiB" << std::setw(11) << "peak MiB" << std::setw(17) << "sim cache MiB"
              << "\n";
    for (const auto& c : f["checkpoints"]) {
      std::cout << std::setw(8) << Fixed(c["percent"], 0) << std::setw(9) << c["frames"].get<int>()
                << std::setw(10) << Fixed(c["wall_s"], 1) << std::setw(12)
                << Fixed(c["segment_frames_per_s"], 1) << std::setw(14)
                << Fixed(c["segment_cpu_ms_per_frame"], 1) << std::setw(8)
                << Fixed(c["segment_push_cpu_ms_per_frame"], 1) << std::setw(8)
                << Fixed(c["segment_writer_cpu_ms_per_frame"], 1) << std::setw(8)
                << Fixed(c["segment_index_ms_per_frame"], 2) << std::setw(10)
                << Fixed(c["rss_mib"], 0) << std::setw(11) << Fixed(c["peak_rss_mib"], 0)
                << std::setw(17) << Fixed(c["simulator_cache_mib"], 0) << "\n";
    }
    std::cout << "(CPU ms/frame of the tenth; Push and writer: those threads' CPU; index*: the "
                 "writer's wall ms in VRTs and manifest.json)\n";
    std::cout << "total: " << Fixed(f["frames_per_s"], 1) << " frames/s wall (foreground "
              << Fixed(f["foreground_frames_per_s"], 1) << ", finish " << Fixed(f["finish_s"], 1)
              << " s), pipeline CPU " << Fixed(f["pipeline_cpu_ms_per_frame"], 1)
              << " ms/frame (renderer " << Fixed(f["renderer_cpu_ms_per_frame"], 1)
              << " ms/frame excluded; foreground Push " << Fixed(f["push_cpu_ms_per_frame"], 1)
              << " CPU ms/frame), publish latency p50 " << Fixed(f["publish_latency_p50_s"], 3)
              << " s p99 " << Fixed(f["publish_latency_p99_s"], 3) << " s, peak RSS "
              << Fixed(f["peak_rss_mib"], 0) << " MiB\n"
              << "output: writer CPU " << Fixed(f["writer_cpu_ms_per_frame"], 2)
              << " ms/frame (own thread; in the kernel "
              << Fixed(f["writer_system_cpu_ms_per_frame"], 2) << "; wall busy "
              << Fixed(f["writer_busy_ms_per_frame"], 2) << "), paint "
              << Fixed(f["paint_ms_per_frame"], 2) << " ms/frame, store "
              << Fixed(f["store_bytes_per_frame"].get<double>() / 1024.0, 1)
              << " KiB/frame; registered " << f["frames_registered"].get<int64_t>() << ", POS only "
              << f["frames_pos_only"].get<int64_t>() << "\n"
              << "tiles written " << f["tiles_written"].get<int64_t>() << " (overviews "
              << f["overview_tiles_written"].get<int64_t>() << "; blocks copied "
              << f["blocks_copied"].get<int64_t>() << ", encoded "
              << f["blocks_encoded"].get<int64_t>() << "; read back "
              << f["tile_reloads"].get<int64_t>() << ", overviews read "
              << f["overview_reads"].get<int64_t>() << ", copied before painting "
              << f["tile_copies"].get<int64_t>() << "), re-renders "
              << f["rerendered_frames"].get<int64_t>() << " (deferred "
              << f["deferred_rerenders"].get<int64_t>() << "), optimizer " << f["optimizer_solves"]
              << " solves (" << f["optimizer_full_solves"] << " over the whole window; mean "
              << Fixed(f["optimizer_mean_solve_ms"], 0) << " ms, CPU "
              << Fixed(f["optimizer_mean_solve_cpu_ms"], 0) << " ms; "
              << Fixed(f["optimizer_cpu_ms_per_frame"], 1)
              << " CPU ms/frame); on disk behind the solution: seams "
              << Fixed(f["mean_seam_lag_px"], 3) << " px, frames "
              << Fixed(f["mean_painted_lag_px"], 3)
              << " px (RMS, mean over solves)\nplacement vs truth mean "
              << Fixed(f["placement_mean_px"], 3) << " px, p95 " << Fixed(f["placement_p95_px"], 3)
              << ", max " << Fixed(f["placement_max_px"], 3) << ", frames over 5 px "
              << f["placement_frames_over_5px"].get<int64_t>() << ", over 20 px "
              << f["placement_frames_over_20px"].get<int64_t>() << "; worst:";
    for (const auto& w : f["placement_worst_frames"]) {
      std::cout << " " << w["index"].get<int64_t>() << " (" << Fixed(w["rmse_px"], 1) << " px"
                << (w["pos_only"].get<bool>() ? ", POS only" : "") << ", "
                << w["neighbours"].get<int64_t>() << " neighbours, " << w["inliers"].get<int>()
                << " inliers)";
    }
    std::cout << "\nplacement by position in the sweep (mean / p95 / max px):";
    for (const auto& b : f["placement_by_sweep_position"]) {
      std::cout << " " << b["position"].get<int>() << ": " << Fixed(b["mean_px"], 2) << " / "
                << Fixed(b["p95_px"], 2) << " / " << Fixed(b["max_px"], 2);
    }
    std::cout << "\nas painted (the mosaic on disk) vs truth mean "
              << Fixed(f["painted_mean_px"], 3) << " px, p95 " << Fixed(f["painted_p95_px"], 3)
              << ", max " << Fixed(f["painted_max_px"], 3) << "; painted vs final placement mean "
              << Fixed(f["painted_lag_mean_px"], 3) << " px, p95 "
              << Fixed(f["painted_lag_p95_px"], 3) << ", max " << Fixed(f["painted_lag_max_px"], 3)
              << ", frames over 1 px " << f["painted_lag_frames_over_1px"].get<int64_t>() << " of "
              << f["painted_frames"].get<int64_t>() << "; settled frames re-rendered "
              << f["settled_rerenders"].get<int64_t>() << " ("
              << f["settled_rerenders_on_leaving"].get<int64_t>()
              << " as they left), frozen lagging " << f["settled_left_lagging"].get<int64_t>();
    std::cout << "\nfusion: images held at the end " << f["held_images"].get<int64_t>() << " ("
              << Fixed(f["held_image_mib"], 0) << " MiB in memory), "
              << f["spilled_images"].get<int64_t>() << " on disk (file "
              << Fixed(f["spill_file_mib"], 0) << " MiB, " << f["spill_reads"].get<int64_t>()
              << " read back"
              << (f["spill_error"].get<std::string>().empty()
                      ? std::string()
                      : "; " + f["spill_error"].get<std::string>())
              << "), oldest neighbour registered to " << f["oldest_neighbour_frames"]
              << " frames back\n";
  }

  if (paced_frames > 0) {
    RunConfig paced;
    paced.frames = paced_frames;
    paced.rate_hz = 25.0;
    paced.store = store + "/paced";
    paced.optimize = optimize;
    const nlohmann::json p = RunMosaicker(paced);
    doc["paced"] = p;
    std::cout << "\nFrames arriving at 25 fps, " << paced_frames
              << " frames: publish latency from arrival p50 "
              << Fixed(p["publish_latency_p50_s"], 3) << " s, p99 "
              << Fixed(p["publish_latency_p99_s"], 3) << " s, max "
              << Fixed(p["publish_latency_max_s"], 3) << " s; pipeline CPU "
              << Fixed(p["pipeline_cpu_ms_per_frame"], 1) << " ms/frame; writer CPU "
              << Fixed(p["writer_cpu_ms_per_frame"], 2) << " ms/frame (in the kernel "
              << Fixed(p["writer_system_cpu_ms_per_frame"], 2) << ")\n"
              << "  taken by the pipeline after arrival p50 " << Fixed(p["intake_lag_p50_s"], 3)
              << " s, p99 " << Fixed(p["intake_lag_p99_s"], 3) << " s, max "
              << Fixed(p["intake_lag_max_s"], 3) << " s; foreground Push "
              << Fixed(p["push_cpu_ms_per_frame"], 1) << " CPU ms/frame; re-renders "
              << p["rerendered_frames"].get<int64_t>() << " (deferred "
              << p["deferred_rerenders"].get<int64_t>() << "), optimizer " << p["optimizer_solves"]
              << " solves\n"
              << "  tiles written " << p["tiles_written"].get<int64_t>() << " (overviews "
              << p["overview_tiles_written"].get<int64_t>() << "; blocks copied "
              << p["blocks_copied"].get<int64_t>() << ", encoded "
              << p["blocks_encoded"].get<int64_t>() << "), publishes "
              << p["publishes"].get<int64_t>() << " (overview updates "
              << p["overview_updates"].get<int64_t>() << ", of them early "
              << p["overview_updates_early"].get<int64_t>() << ", "
              << p["overview_updates_in_publish"].get<int64_t>() << " done inside a publish; "
              << p["overview_slices"].get<int64_t>() << " slices between publishes; refreshed "
              << p["refresh_tiles_written"].get<int64_t>() << " level-0 tiles in "
              << p["refresh_slices"].get<int64_t>() << " slices)\n";
    std::cout << std::setw(8) << "% done" << std::setw(9) << "frames" << std::setw(14)
              << "CPU ms/frame" << std::setw(8) << "writer" << std::setw(8) << "kernel"
              << std::setw(10) << "tiles/fr" << std::setw(11) << "published" << std::setw(9)
              << "p50 s" << std::setw(9) << "p99 s" << std::setw(9) << "max s" << std::setw(9)
              << "waited" << std::setw(10) << "RSS MiB" << std::setw(11) << "peak MiB"
              << "\n";
    for (const auto& c : p["checkpoints"]) {
      std::cout << std::setw(8) << Fixed(c["percent"], 0) << std::setw(9) << c["frames"].get<int>()
                << std::setw(14) << Fixed(c["segment_cpu_ms_per_frame"], 1) << std::setw(8)
                << Fixed(c["segment_writer_cpu_ms_per_frame"], 1) << std::setw(8)
                << Fixed(c["segment_writer_system_cpu_ms_per_frame"], 1) << std::setw(10)
                << Fixed(c["segment_tiles_written_per_frame"], 2) << std::setw(11)
                << c["segment_frames_published"].get<int64_t>() << std::setw(9)
                << Fixed(c["segment_publish_latency_p50_s"], 3) << std::setw(9)
                << Fixed(c["segment_publish_latency_p99_s"], 3) << std::setw(9)
                << Fixed(c["segment_publish_latency_max_s"], 3) << std::setw(9)
                << Fixed(c["segment_paint_wait_s"], 2) << std::setw(10) << Fixed(c["rss_mib"], 0)
                << std::setw(11) << Fixed(c["peak_rss_mib"], 0) << "\n";
    }
    std::cout << "(each tenth of the paced flight: CPU and writer CPU ms/frame, of the writer's "
                 "the kernel's, tiles written per "
                 "frame, frames published in it and their publish latency from arrival; waited: "
                 "seconds the "
                 "caller's Paint waited for the writer, the store's back-pressure)\n";
    PrintSlowestFrames(p["slowest_frames"]);
  }

  if (!compare.empty()) {
    const std::string self = std::filesystem::canonical("/proc/self/exe").string();
    nlohmann::json rows = nlohmann::json::array();
    std::cout << "\nSame first frames, each method in its own process (timeout " << timeout_s
              << " s):\n"
              << std::left << std::setw(26) << "method" << std::right << std::setw(8) << "frames"
              << std::setw(11) << "wall s" << std::setw(10) << "CPU s" << std::setw(11)
              << "peak MiB" << std::setw(9) << "success" << std::setw(12) << "wall ratio"
              << std::setw(12) << "mem ratio"
              << "  status\n";
    for (int n : compare) {
      nlohmann::json ours = RunChild(self, "irmosaic", n, timeout_s, store);
      ours["method"] = "irmosaic Mosaicker";
      rows.push_back(ours);
      for (const std::string kind : {"stitcher", "orb"}) {
        nlohmann::json r = RunChild(self, kind, n, timeout_s, store);
        r["wall_ratio_to_irmosaic"] =
            r.value("seconds", 0.0) / std::max(1e-9, ours.value("seconds", 0.0));
        r["memory_ratio_to_irmosaic"] =
            r.value("peak_rss_mib", 0.0) / std::max(1e-9, ours.value("peak_rss_mib", 0.0));
        rows.push_back(r);
      }
    }
    for (const auto& r : rows) {
      std::cout << std::left << std::setw(26) << r.value("method", std::string("?")) << std::right
                << std::setw(8) << r.value("frames", 0) << std::setw(11)
                << Fixed(r.value("seconds", 0.0), 1) << std::setw(10)
                << Fixed(r.value("cpu_s", 0.0), 1) << std::setw(11)
                << Fixed(r.value("peak_rss_mib", 0.0), 0) << std::setw(9)
                << (r.value("success", false) ? "yes" : "no") << std::setw(12)
                << (r.contains("wall_ratio_to_irmosaic") ? Fixed(r["wall_ratio_to_irmosaic"], 2)
                                                         : std::string("1"))
                << std::setw(12)
                << (r.contains("memory_ratio_to_irmosaic") ? Fixed(r["memory_ratio_to_irmosaic"], 2)
                                                           : std::string("1"))
                << "  " << r.value("status", std::string("")) << "\n";
    }
    doc["compare"] = rows;
  }
  if (!json_path.empty()) std::ofstream(json_path) << doc.dump(2) << "\n";
  return 0;
}
