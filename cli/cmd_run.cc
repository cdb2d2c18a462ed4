// `irmosaic run`: a whole flight (frames + POS + camera) into a live georeferenced store.
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "args.h"
#include "commands.h"
#include "irmosaic/error.h"
#include "irmosaic/frame_source.h"
#include "irmosaic/mosaicker.h"

namespace irmosaic::cli {
namespace {

using Clock = std::chrono::steady_clock;

// Progress on stderr: one rewritten line on a terminal, plain lines otherwise.
class Progress {
 public:
  explicit Progress(int64_t total) : total_(total), tty_(isatty(STDERR_FILENO) != 0) {}
  void Update(int64_t done, bool force = false) {
    const auto now = Clock::now();
    const double since = std::chrono::duration<double>(now - last_).count();
    const bool milestone = !tty_ && (done % 100 == 0);
    if (!force && (tty_ ? since < 0.2 : !milestone)) return;
    last_ = now;
    const double elapsed = std::chrono::duration<double>(now - start_).count();
    const double rate = elapsed > 0 ? done / elapsed : 0.0;
    char line[200];
    if (total_ > 0) {
      const double eta = rate > 0 ? (total_ - done) / rate : 0.0;
      std::snprintf(line, sizeof(line), "run: %lld/%lld frames  %.1f frames/s  ETA %.0f s",
                    static_cast<long long>(done), static_cast<long long>(total_), rate, eta);
    } else {
      std::snprintf(line, sizeof(line), "run: %lld frames  %.1f frames/s",
                    static_cast<long long>(done), rate);
    }
    std::cerr << (tty_ ? "\r" : "") << line << (tty_ ? "   " : "\n") << std::flush;
  }
  void Done() {
    if (tty_) std::cerr << "\n";
  }

 private:
  int64_t total_;
  bool tty_;
  Clock::time_point start_ = Clock::now(), last_ = Clock::now() - std::chrono::seconds(1);
};

}  // namespace

int RunRun(int argc, char** argv) {
  Args args("run",
            "Mosaics a flight into a live georeferenced store (tiled GeoTIFFs, mosaic.vrt,\n"
            "manifest.json, frames.gpkg, a QGIS layer file) that GIS tools read while it grows.");
  args.Option("--frames", "video file, folder of images, or frame list CSV (index,time_s,file)",
              std::nullopt, "PATH");
  args.Option("--pos", "POS log, CSV (docs/formats.md)", std::nullopt, "FILE");
  args.Option("--camera", "camera file, JSON (docs/formats.md)", std::nullopt, "FILE");
  args.Option("--out", "output store folder", std::nullopt, "STORE");
  args.Flag("--resume", "continue an interrupted store");
  args.Flag("--overwrite", "replace an existing store");
  args.Option("--gsd", "mosaic ground sample distance, metres (0: nadir GSD of the camera)", "0",
              "M");
  args.Option("--ground-height", "ground ellipsoidal height, metres", "0", "M");
  args.Option("--tile-size", "tile size, pixels", "512", "N");
  args.Option("--compression", "tile compression: ZSTD, DEFLATE, LZW or NONE", "ZSTD", "NAME");
  args.Option("--window", "frames in the global optimization window", "300", "N");
  args.Option("--short-window",
              "frames most background solves refine; one solve in 4, and the last, refine the "
              "whole window (0: every solve does)",
              "100", "N");
  args.Option("--max-rerenders",
              "frames a background solve re-renders at most, those that moved most (0: no limit; "
              "the final solve re-renders every frame that moved)",
              "16", "N");
  args.Flag("--no-optimize", "real-time mapping only (no global optimization)");
  args.Flag("--no-settled-rerenders",
            "do not re-render frames that left the optimization window where the solution put "
            "them: faster (about a fifth), but the finished mosaic then shows many frames at an "
            "earlier placement (docs/fusion.md, \"The mosaic on disk\")");
  args.Flag("--no-planned-extent",
            "do not size the store to the flight's POS footprints ahead (the GDAL plug-in, and "
            "QGIS through it, then show the painted extent of when they opened the store)");
  args.Option("--pos-sigma", "POS position accuracy (1 sigma), metres", "2", "M");
  args.Option("--att-sigma", "POS attitude accuracy (1 sigma), degrees", "0.3", "DEG");
  args.Option("--radius", "coarse search radius around the POS prediction, pixels", "64", "PX");
  args.Option("--wide-radius",
              "a pair that fails at --radius is tried once more at this radius (0: not), pixels",
              "128", "PX");
  args.Option("--max-gap", "POS gap beyond which frames get no pose, seconds", "1", "S");
  args.Option("--max-range",
              "ground farther than this from the camera is clipped off a frame (with a warning), "
              "metres",
              "30000", "M");
  args.Option("--fps", "frame rate of a video or image folder", "25", "HZ");
  args.Option("--t0", "time of the first frame of a video or image folder, seconds", "0", "S");
  args.Option("--threads", "OpenCV threads", "2", "N");
  args.Option("--registration-threads", "pairs of a new frame registered at once", "2", "N");
  args.Option("--max-cached-tiles",
              "store tiles kept in memory (about 3x this many in use; 768 KiB each at 512 px, "
              "16 bits)",
              "64", "N");
  args.Option("--images-in-memory",
              "frame images kept in memory; older ones the optimizer may re-render wait in an "
              "unnamed file in the store folder (0: all in memory)",
              "32", "N");
  args.Option("--publish-interval",
              "seconds between publishes of a new generation (the latency a frame waits for its "
              "publish; longer: fewer tile writes)",
              "0.25", "S");
  args.Option("--sync-interval",
              "seconds between flushes of the store's file system to disk (0: the kernel's own "
              "write-back, up to ~30 s)",
              "2", "S");
  args.Option("--report", "JSON report (default: STORE/run_report.json)", "", "FILE");
  int exit_code = 0;
  if (!args.Parse(argc, argv, &exit_code)) return exit_code;
  if (args.Has("--resume") && args.Has("--overwrite")) {
    std::cerr << "irmosaic run: --resume and --overwrite exclude each other\n";
    return 2;
  }
  cv::setNumThreads(std::max(1, args.GetInt("--threads")));

  PosTrack::Options pos_options;
  pos_options.max_gap_s = args.GetDouble("--max-gap");
  PosTrack pos = PosTrack::LoadCsv(args.Get("--pos"), pos_options);
  CameraModel camera = CameraModel::LoadJson(args.Get("--camera"));
  FrameSource::Options source_options;
  source_options.fps = args.GetDouble("--fps");
  source_options.t0_s = args.GetDouble("--t0");
  std::unique_ptr<FrameSource> source = FrameSource::Open(args.Get("--frames"), source_options);

  MosaickerOptions options;
  options.store_path = args.Get("--out");
  options.mode = args.Has("--resume")      ? TileStoreOptions::Mode::kResume
                 : args.Has("--overwrite") ? TileStoreOptions::Mode::kOverwrite
                                           : TileStoreOptions::Mode::kCreate;
  options.gsd_m = args.GetDouble("--gsd");
  options.ground_height_m = args.GetDouble("--ground-height");
  options.tile_size = args.GetInt("--tile-size");
  options.compression = args.Get("--compression");
  options.fusion.window_frames = args.GetInt("--window");
  options.fusion.short_window_frames = args.GetInt("--short-window");
  options.fusion.max_rerenders_per_solve = args.GetInt("--max-rerenders");
  options.fusion.optimize = !args.Has("--no-optimize");
  // A recorded flight is a product, not a live feed: every frame on disk where the solution
  // puts it (the library's default is off, for the publish latency of a live feed).
  options.fusion.rerender_settled_frames = !args.Has("--no-settled-rerenders");
  options.planned_extent = !args.Has("--no-planned-extent");
  options.registration_threads = args.GetInt("--registration-threads");
  options.max_cached_tiles = args.GetInt("--max-cached-tiles");
  options.sync_interval_s = args.GetDouble("--sync-interval");
  options.publish_interval_s = args.GetDouble("--publish-interval");
  options.images_in_memory = args.GetInt("--images-in-memory");
  options.pos_position_sigma_m = args.GetDouble("--pos-sigma");
  options.pos_attitude_sigma_deg = args.GetDouble("--att-sigma");
  options.search_radius_px = args.GetDouble("--radius");
  options.wide_search_radius_px = args.GetDouble("--wide-radius");
  options.max_range_m = args.GetDouble("--max-range");
  Mosaicker mosaicker(options, camera, pos);

  const auto start = Clock::now();
  Progress progress(source->size());
  int64_t done = 0, bad_frames = 0;
  const int64_t resume_after = mosaicker.resumed_last_index();
  if (resume_after >= 0) {
    // The store recorded every placement; the frames still in the optimizer's window at the
    // cut are pushed again (not painted) to rebuild its state, the older ones are not.
    source->SkipThrough(mosaicker.resume_replay_from() - 1);
    if (!mosaicker.resume_warning().empty()) {
      std::cerr << "run: warning: " << mosaicker.resume_warning() << "\n";
    }
    std::cerr << "run: resuming after frame " << resume_after << " (replaying frames "
              << mosaicker.resume_replay_from() << "-" << resume_after << ")\n";
    mosaicker.SetReplay(true);
  }
  SourceFrame frame;
  std::string problem;
  int64_t locked_reported = 0;
  while (true) {
    const FrameSource::Status status = source->Next(&frame, &problem);
    if (status == FrameSource::Status::kEnd) {
      if (!problem.empty()) std::cerr << "\nrun: warning: " << problem << "\n";
      break;
    }
    if (resume_after >= 0 && frame.index > resume_after) mosaicker.SetReplay(false);
    ++done;
    if (status == FrameSource::Status::kBadFrame) {
      ++bad_frames;
      std::cerr << "\nrun: warning: skipped " << problem << "\n";
      continue;
    }
    const PushResult result = mosaicker.Push(frame.index, frame.time_s, frame.image);
    if (!result.placed()) std::cerr << "\nrun: warning: skipped " << result.reason << "\n";
    if (!result.warning.empty()) std::cerr << "\nrun: warning: " << result.warning << "\n";
    // Said while it happens, not only in the summary: a program holding frames.gpkg locked
    // (docs/store.md, "Publishing and atomicity") delays the footprints, not the mosaic.
    if (done % 250 == 0 && mosaicker.store() != nullptr) {
      const int64_t locked = mosaicker.store()->stats().frames_gpkg_locked;
      if (locked > locked_reported) {
        std::cerr << "\nrun: warning: another program holds "
                  << (std::filesystem::path(options.store_path) / "frames.gpkg").string()
                  << " locked; the footprints wait in manifest.json until it lets go\n";
        locked_reported = locked;
      }
    }
    progress.Update(done);
  }
  mosaicker.SetReplay(false);
  progress.Update(done, true);
  progress.Done();
  // A store that fails to close (frames.gpkg locked by another program past the closing wait,
  // a full disk) still gets the run's placements and report when they can be written: the
  // fusion has finished, and the error is said last, after the summary, with its fix.
  std::string finish_error;
  try {
    mosaicker.Finish();
  } catch (const OutputError& e) {
    finish_error = e.what();
  }
  std::string placements_path =
      (std::filesystem::path(options.store_path) / "placements.json").string();
  try {
    mosaicker.WritePlacements(placements_path);
  } catch (const OutputError& e) {
    if (finish_error.empty()) throw;
    std::cerr << "run: warning: " << e.what() << "\n";
    placements_path.clear();
  }
  const MosaickerSummary s = mosaicker.summary();
  const double elapsed = std::chrono::duration<double>(Clock::now() - start).count();
  std::cerr << "run: " << s.frames_placed << " frames placed (" << s.frames_registered
            << " registered, " << s.frames_pos_only << " POS only), "
            << s.frames_skipped + bad_frames << " skipped, in " << elapsed << " s ("
            << (elapsed > 0 ? done / elapsed : 0.0) << " frames/s)\n"
            << "run: " << s.fusion.solves << " optimizer solves, " << s.generations_published
            << " generations published, publish latency p50 " << s.publish_latency_p50_s
            << " s p99 " << s.publish_latency_p99_s << " s\n";
  if (options.fusion.optimize && !options.fusion.rerender_settled_frames) {
    std::cerr << "run: frames older than the optimization window show the placement they were "
                 "last painted at, not always their final one (--no-settled-rerenders)\n";
  } else if (options.fusion.optimize) {
    const int64_t rerendered = s.fusion.rerendered_frames + s.fusion.settled_rerenders_on_leaving;
    std::cerr << "run: " << rerendered << " re-renders where the optimizer moved frames ("
              << s.fusion.settled_rerenders << " after they left its window); ";
    if (s.fusion.settled_left_lagging == 0) {
      std::cerr << "every frame is on disk within "
                << std::max(options.fusion.settled_rerender_threshold_px,
                            options.fusion.rerender_threshold_px)
                << " px of its final placement\n";
    } else {
      std::cerr << s.fusion.settled_left_lagging
                << " frames keep an earlier placement (their images could not be read back)\n";
    }
  }
  const int64_t frames_gpkg_locked =
      mosaicker.store() ? mosaicker.store()->stats().frames_gpkg_locked : 0;
  if (frames_gpkg_locked > 0) {
    std::cerr << "run: warning: another program held frames.gpkg locked at " << frames_gpkg_locked
              << " of its updates; those footprints waited in manifest.json (frames.pending)"
              << (finish_error.empty() ? " and reached frames.gpkg with a later update\n"
                                       : ", where the closing update had to leave them\n");
  }
  std::cerr << "run: store " << options.store_path
            << " (open mosaic.vrt or irmosaic.qlr in QGIS; irmosaic_live.qlr, with the IRMOSAIC "
               "plug-in, shows it grow live)\n";
  const nlohmann::json report = {
      {"frames_read", done},
      {"frames_placed", s.frames_placed},
      {"frames_registered", s.frames_registered},
      {"frames_pos_only", s.frames_pos_only},
      {"frames_skipped", s.frames_skipped + bad_frames},
      {"seconds", elapsed},
      {"frames_per_second", elapsed > 0 ? done / elapsed : 0.0},
      {"gsd_m", s.gsd_m},
      {"origin", {{"lat_deg", s.origin_lat_deg}, {"lon_deg", s.origin_lon_deg}}},
      {"generations_published", s.generations_published},
      {"publish_latency_s",
       {{"p50", s.publish_latency_p50_s},
        {"p99", s.publish_latency_p99_s},
        {"max", s.publish_latency_max_s}}},
      {"optimizer",
       {{"solves", s.fusion.solves},
        {"max_solve_ms", s.fusion.max_solve_ms},
        {"mean_solve_ms", s.fusion.solves ? s.fusion.total_solve_ms / s.fusion.solves : 0.0},
        {"rerendered_frames", s.fusion.rerendered_frames},
        {"settled_rerenders", s.fusion.settled_rerenders},
        {"settled_rerenders_on_leaving", s.fusion.settled_rerenders_on_leaving},
        {"settled_left_lagging", s.fusion.settled_left_lagging},
        {"settled_repainted_after_solve", s.fusion.settled_repainted_after_solve},
        {"mean_seam_lag_px", s.fusion.mean_seam_lag_px},
        {"mean_painted_lag_px", s.fusion.mean_painted_lag_px}}},
      {"pairs", {{"tried", s.fusion.pairs_tried}, {"ok", s.fusion.pairs_ok}}},
      {"frames_gpkg_locked", frames_gpkg_locked},
      {"held_images",
       {{"in_memory_limit", options.images_in_memory},
        {"file_mib", static_cast<double>(s.fusion.spill_file_bytes) / 1048576.0},
        {"read_back", s.fusion.spill_reads},
        {"file_error", s.fusion.spill_error}}},
      {"placements",
       placements_path.empty() ? nlohmann::json(nullptr) : nlohmann::json(placements_path)},
      {"finish_error",
       finish_error.empty() ? nlohmann::json(nullptr) : nlohmann::json(finish_error)}};
  const std::string report_path =
      args.Get("--report").empty()
          ? (std::filesystem::path(options.store_path) / "run_report.json").string()
          : args.Get("--report");
  if (!(std::ofstream(report_path) << report.dump(2) << "\n")) {
    std::cerr << "run: warning: cannot write " << report_path << " (disk full or not writable?)\n";
  }
  if (!s.fusion.spill_error.empty()) {
    std::cerr << "irmosaic run: warning: the frame image file in the store folder failed ("
              << s.fusion.spill_error
              << "): images it refused stayed in memory, a failed read skipped that re-render. "
                 "Fix: free disk space there, or --images-in-memory 0\n";
  }
  if (!finish_error.empty()) {
    std::cerr << "irmosaic run: error: " << finish_error << "\n";
    return 1;
  }
  if (s.frames_placed == 0) {
    std::cerr << "irmosaic run: error: no frame could be placed (see the warnings above)\n";
    return 1;
  }
  return 0;
}

}  // namespace irmosaic::cli
