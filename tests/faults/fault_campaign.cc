// Issue 11's fault campaign against the real command line (scripts/faults.sh runs it in CI):
//  1. kill -9 of `irmosaic run` at seeded random moments of a small simulated flight; after each
//     kill the store must open and read without error in GDAL (mosaic.vrt, and the store folder
//     through the IRMOSAIC plug-in from GDAL_DRIVER_PATH); `--resume` must complete it; the
//     resumed placements must agree with an uninterrupted run within 0.5 px.
//  2. reader processes opening and reading the store in a loop while a run writes it (half
//     through mosaic.vrt, half through the plug-in): zero read errors, no torn tile (a tile read
//     while partly written fails to decode, which GDAL reports as an error).
// Prints the figures and exits non-zero on any failure.
#include <cpl_error.h>
#include <gdal_priv.h>
#include <ogrsf_frmts.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <nlohmann/json.hpp>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "irmosaic/evaluator.h"
#include "irmosaic/simulator.h"
#include "test_data.h"

namespace irmosaic {
namespace {
namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

struct Config {
  std::string cli;
  std::string plugin_dir;
  std::string work;
  std::string json;
  int runs = 20;
  int readers = 4;
  int frames = 40;
  // --window of every run: shorter than the flight, so that frames leave the optimizer's
  // window before most kills and the resume must start from the placements the store recorded
  // (docs/reliability.md).
  int window = 16;
  // --short-window: below --window, so that most solves refine part of the window (one in 4
  // the whole of it) and a resume must replay which (docs/fusion.md, "Short and full solves").
  int short_window = 8;
  uint64_t seed = 11;
};

double Seconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

// GDAL errors and warnings raised while reading, counted per thread of this process.
struct ErrorCount {
  int failures = 0;
  int warnings = 0;
  std::string first;
};
thread_local ErrorCount* g_errors = nullptr;
void CPL_STDCALL CountErrors(CPLErr level, CPLErrorNum, const char* message) {
  if (g_errors == nullptr) return;
  if (level >= CE_Failure) {
    if (g_errors->failures++ == 0 && g_errors->first.empty()) g_errors->first = message;
  } else if (level == CE_Warning) {
    if (g_errors->warnings++ == 0 && g_errors->first.empty()) g_errors->first = message;
  }
}

// Opens `path` (mosaic.vrt, or the store folder through the plug-in) and reads every band at
// full resolution and at its first overview. "" if clean, else the first problem.
std::string ReadStore(const std::string& path, bool plugin, int64_t* pixels_read) {
  ErrorCount errors;
  g_errors = &errors;
  CPLPushErrorHandler(CountErrors);
  std::string problem;
  {
    const char* const only_plugin[] = {"IRMOSAIC", nullptr};
    GDALDatasetUniquePtr ds(
        GDALDataset::FromHandle(GDALOpenEx(path.c_str(), GDAL_OF_RASTER | GDAL_OF_READONLY,
                                           plugin ? only_plugin : nullptr, nullptr, nullptr)));
    if (!ds) {
      problem = "cannot open " + path;
    } else {
      const int w = ds->GetRasterXSize(), h = ds->GetRasterYSize();
      std::vector<uint16_t> row_block;
      constexpr int kRows = 256;
      for (int b = 1; b <= ds->GetRasterCount() && problem.empty(); ++b) {
        GDALRasterBand* band = ds->GetRasterBand(b);
        for (int level = -1; level < std::min(1, band->GetOverviewCount()); ++level) {
          GDALRasterBand* src = level < 0 ? band : band->GetOverview(level);
          const int sw = level < 0 ? w : src->GetXSize(), sh = level < 0 ? h : src->GetYSize();
          row_block.resize(static_cast<size_t>(sw) * kRows);
          for (int y = 0; y < sh && problem.empty(); y += kRows) {
            const int rows = std::min(kRows, sh - y);
            if (src->RasterIO(GF_Read, 0, y, sw, rows, row_block.data(), sw, rows, GDT_UInt16, 0,
                              0) != CE_None) {
              problem = "read failed at band " + std::to_string(b) + " row " + std::to_string(y);
            }
            *pixels_read += static_cast<int64_t>(sw) * rows;
          }
        }
      }
    }
  }
  CPLPopErrorHandler();
  g_errors = nullptr;
  if (problem.empty() && errors.failures > 0) problem = "GDAL error";
  if (!problem.empty() && !errors.first.empty()) problem += ": " + errors.first;
  if (problem.empty() && errors.warnings > 0) problem = "GDAL warning: " + errors.first;
  return problem;
}

// The store has published painted tiles: its manifest's bounds are set. The manifest of a store
// that has published nothing painted yet holds `"bounds_px": null` (and no level-0 tiles), which
// the plug-in rightly refuses ("no tiles yet": GDAL has no 0 x 0 raster). Testing for the key
// alone counted those refusals as read errors (the campaign's "plug-in readers fail" finding).
bool HasTiles(const std::string& store) {
  std::ifstream in(store + "/manifest.json");
  if (!in) return false;
  const nlohmann::json m = nlohmann::json::parse(in, nullptr, false);
  return m.is_object() && m.contains("bounds_px") && m["bounds_px"].is_object();
}

// Starts `irmosaic run` on the flight into `store` (stderr to `log`); returns its pid.
pid_t StartRun(const Config& config, const std::string& store, bool resume,
               const std::string& log) {
  const std::string flight = config.work + "/flight";
  std::fflush(nullptr);  // Or the child's freopen flushes our buffered output a second time.
  const pid_t child = fork();
  if (child == 0) {
    if (!std::freopen(log.c_str(), "w", stderr)) _exit(126);
    if (!std::freopen("/dev/null", "w", stdout)) _exit(126);
    const std::string frames = flight + "/frames.csv", pos = flight + "/pos.csv",
                      camera = flight + "/camera.json";
    const std::string window = std::to_string(config.window);
    const std::string short_window = std::to_string(config.short_window);
    execl(config.cli.c_str(), "irmosaic", "run", "--frames", frames.c_str(), "--pos", pos.c_str(),
          "--camera", camera.c_str(), "--out", store.c_str(), "--window", window.c_str(),
          "--short-window", short_window.c_str(), resume ? "--resume" : nullptr, nullptr);
    _exit(127);
  }
  return child;
}

int WaitExit(pid_t child) {
  int status = 0;
  waitpid(child, &status, 0);
  return WIFEXITED(status) ? WEXITSTATUS(status) : -WTERMSIG(status);
}

std::string Tail(const std::string& path) {
  std::ifstream in(path);
  std::string text((std::istreambuf_iterator<char>(in)), {});
  return text.size() > 600 ? text.substr(text.size() - 600) : text;
}

// Worst placement difference (grid points of each frame, mosaic px) of `run` against `ref`.
struct Agreement {
  int frames = 0;
  int missing = 0;
  double max_px = 0.0;
  double mean_rmse_px = 0.0;
};
Agreement Compare(const std::string& ref_store, const std::string& store) {
  const Placements ref = Placements::LoadJson(ref_store + "/placements.json");
  const Placements run = Placements::LoadJson(store + "/placements.json");
  const PlacementScore score = Evaluator(ref).ScorePlacements(run);
  Agreement a;
  a.frames = score.frames_scored;
  a.missing = score.frames_missing;
  a.mean_rmse_px = score.rmse_px.mean;
  for (const FrameScore& f : score.frames) a.max_px = std::max(a.max_px, f.max_px);
  return a;
}

// Frames of the store's placements.json without a record in its frames.gpkg (-1: unreadable).
// frames.gpkg follows the tiles every 2 s; until session 32 a kill lost the records of the last
// seconds' frames and --resume did not bring them back.
int FramesWithoutRecord(const std::string& store) {
  const Placements run = Placements::LoadJson(store + "/placements.json");
  GDALDatasetUniquePtr gpkg(
      GDALDataset::Open((store + "/frames.gpkg").c_str(), GDAL_OF_VECTOR | GDAL_OF_READONLY));
  OGRLayer* layer = gpkg ? gpkg->GetLayerByName("frames") : nullptr;
  if (layer == nullptr) return -1;
  std::set<int64_t> recorded;
  for (auto& feature : *layer) recorded.insert(feature->GetFieldAsInteger64("frame_index"));
  int missing = 0;
  for (const Placement& p : run.frames) missing += recorded.count(p.index) ? 0 : 1;
  return missing;
}

int Main(const Config& config) {
  const auto campaign_start = Clock::now();
  fs::remove_all(config.work);
  fs::create_directories(config.work);
  // The plug-in must be found by GDALAllRegister, in this process and the forked readers.
  setenv("GDAL_DRIVER_PATH", config.plugin_dir.c_str(), 1);
  GDALAllRegister();
  if (GetGDALDriverManager()->GetDriverByName("IRMOSAIC") == nullptr) {
    std::cerr << "fault_campaign: the IRMOSAIC plug-in is not in " << config.plugin_dir << "\n";
    return 2;
  }
  {
    SynthOptions options;
    options.ground_path = testing::SamplePath("sample_flight/ground_naip_2019.tif");
    options.seed = config.seed;
    options.frame_count = config.frames;
    options.altitude_m = 600;
    options.heading_deg = 80;
    options.frames_per_sweep = 8;
    options.sensor.noise_psnr_db = 35.0;
    FlightSimulator(options).WriteFlight(config.work + "/flight");
  }
  int failures = 0;
  auto fail = [&](const std::string& what) {
    ++failures;
    std::cout << "FAIL " << what << "\n";
  };

  // The uninterrupted run: reference placements and the run's duration.
  const std::string ref = config.work + "/ref.irmosaic";
  auto start = Clock::now();
  if (WaitExit(StartRun(config, ref, false, ref + ".log")) != 0) {
    std::cout << "FAIL the uninterrupted run: " << Tail(ref + ".log") << "\n";
    return 1;
  }
  const double run_s = Seconds(start);
  std::printf("uninterrupted run: %d frames in %.2f s (--window %d --short-window %d)\n",
              config.frames, run_s, config.window, config.short_window);

  // 1. Kills at random moments over the whole run (startup, painting, the final publish).
  std::mt19937_64 random(config.seed);
  std::uniform_real_distribution<double> moment(0.02, 1.0);
  int killed = 0, finished_first = 0, published_count = 0, unpainted = 0, loads = 0, resumed = 0;
  double worst_px = 0.0, resume_s = 0.0;
  int64_t pixels = 0;
  for (int i = 0; i < config.runs; ++i) {
    const std::string store = config.work + "/kill" + std::to_string(i) + ".irmosaic";
    const double kill_at_s = moment(random) * run_s;
    const pid_t child = StartRun(config, store, false, store + ".log");
    std::this_thread::sleep_for(std::chrono::duration<double>(kill_at_s));
    kill(child, SIGKILL);
    const int exit_code = WaitExit(child);
    if (exit_code == -SIGKILL) {
      ++killed;
    } else {
      ++finished_first;  // The run ended before the kill (the machine was faster this time).
    }
    const bool published = fs::exists(store + "/manifest.json");
    std::string vrt_problem = "nothing published", plugin_problem = "nothing published";
    const bool painted = HasTiles(store);
    if (published) {
      ++published_count;
      vrt_problem = ReadStore(store + "/mosaic.vrt", false, &pixels);
      plugin_problem = ReadStore(store, true, &pixels);
      // Killed after the store's first (empty) index but before any painted tile: the plug-in
      // must refuse with its clear message (GDAL has no 0 x 0 raster); that refusal is right.
      if (!painted && plugin_problem.find("no tiles yet") != std::string::npos) {
        plugin_problem.clear();
        ++unpainted;
      }
      if (vrt_problem.empty() && plugin_problem.empty()) ++loads;
    }
    start = Clock::now();
    const int resume_code = WaitExit(StartRun(config, store, true, store + ".resume.log"));
    resume_s += Seconds(start);
    std::string line = "run " + std::to_string(i) + ": killed at " +
                       std::to_string(kill_at_s).substr(0, 5) + " s" +
                       (exit_code == -SIGKILL ? "" : " (had finished)") +
                       (published ? "" : ", nothing published yet");
    if (published && !vrt_problem.empty()) fail(line + ": mosaic.vrt: " + vrt_problem);
    if (published && !plugin_problem.empty()) fail(line + ": plug-in: " + plugin_problem);
    if (resume_code != 0) {
      fail(line + ": --resume exited " + std::to_string(resume_code) + ": " +
           Tail(store + ".resume.log"));
      continue;
    }
    ++resumed;
    const std::string after_vrt = ReadStore(store + "/mosaic.vrt", false, &pixels);
    const std::string after_plugin = ReadStore(store, true, &pixels);
    if (!after_vrt.empty() || !after_plugin.empty()) {
      fail(line + ": resumed store does not read: " + after_vrt + " " + after_plugin);
    }
    const Agreement a = Compare(ref, store);
    worst_px = std::max(worst_px, a.max_px);
    const int unrecorded = FramesWithoutRecord(store);
    std::printf("%s; resumed: %d frames compared, %d missing, max %.3f px, %d without a record\n",
                line.c_str(), a.frames, a.missing, a.max_px, unrecorded);
    if (a.missing > 0 || a.frames == 0) fail(line + ": frames missing after --resume");
    if (unrecorded != 0) {
      fail(line + ": " + std::to_string(unrecorded) + " frames without a record in frames.gpkg");
    }
    if (!(a.max_px < 0.5)) fail(line + ": placement differs by " + std::to_string(a.max_px));
  }

  // 2. Readers during a run.
  const std::string live = config.work + "/live.irmosaic";
  std::vector<std::pair<pid_t, int>> readers;  // pid, pipe read end
  const std::string done_flag = config.work + "/live.done";
  const pid_t writer = StartRun(config, live, false, live + ".log");
  for (int r = 0; r < config.readers; ++r) {
    int fds[2];
    if (pipe(fds) != 0) return 2;
    std::fflush(nullptr);
    const pid_t reader = fork();
    if (reader == 0) {
      close(fds[0]);
      const bool plugin = r % 2 == 1;
      int reads = 0, problems = 0;
      int64_t reader_pixels = 0;
      std::string first, last;
      while (!fs::exists(done_flag)) {
        // Readers start at the first generation with tiles (the plug-in refuses an empty
        // store: GDAL has no 0 x 0 raster), then read in a loop until the run ends.
        if (!HasTiles(live)) {
          std::this_thread::sleep_for(std::chrono::milliseconds(5));
          continue;
        }
        const std::string p =
            ReadStore(plugin ? live : live + "/mosaic.vrt", plugin, &reader_pixels);
        ++reads;
        if (!p.empty() && problems++ == 0) first = p;
        if (!p.empty()) last = p;
      }
      std::ostringstream report;
      report << reads << " " << problems << " " << reader_pixels << " first: " << first
             << " last: " << last;
      const std::string text = report.str();
      if (write(fds[1], text.data(), text.size()) < 0) _exit(2);
      _exit(0);
    }
    close(fds[1]);
    readers.push_back({reader, fds[0]});
  }
  const int live_code = WaitExit(writer);
  std::ofstream(done_flag) << "";
  int total_reads = 0, total_problems = 0;
  for (size_t r = 0; r < readers.size(); ++r) {
    std::string report(4096, '\0');
    ssize_t got = 0, n = 0;
    while ((n = read(readers[r].second, report.data() + got, report.size() - got)) > 0) got += n;
    report.resize(static_cast<size_t>(std::max<ssize_t>(0, got)));
    close(readers[r].second);
    WaitExit(readers[r].first);
    int reads = 0, problems = -1;
    int64_t reader_pixels = 0;
    std::istringstream(report) >> reads >> problems >> reader_pixels;
    std::printf("reader %zu (%s): %d full reads, %d with errors, %.1f Mpx read\n", r,
                r % 2 == 1 ? "plug-in" : "mosaic.vrt", reads, problems, reader_pixels / 1e6);
    total_reads += reads;
    total_problems += problems < 0 ? 1 : problems;
    if (problems != 0) fail("reader " + std::to_string(r) + ": " + report);
    if (reads < 2) fail("reader " + std::to_string(r) + " did not overlap the run: " + report);
  }
  if (live_code != 0) fail("the run with readers exited " + std::to_string(live_code));

  const double campaign_s = Seconds(campaign_start);
  std::printf(
      "kills: %d runs, %d killed mid-run, %d finished before the kill; %d stores loaded after "
      "the kill (of %d with an index, %d of them with no painted tile yet), %d resumed; worst "
      "placement difference %.3f px; mean "
      "resume %.2f s\nreaders: %d processes, %d full reads, %d errors\ncampaign %.1f s, %d "
      "failures\n",
      config.runs, killed, finished_first, loads, published_count, unpainted, resumed, worst_px,
      resumed ? resume_s / config.runs : 0.0, config.readers, total_reads, total_problems,
      campaign_s, failures);
  if (!config.json.empty()) {
    const nlohmann::json report = {{"runs", config.runs},
                                   {"frames", config.frames},
                                   {"seed", config.seed},
                                   {"window", config.window},
                                   {"short_window", config.short_window},
                                   {"uninterrupted_run_s", run_s},
                                   {"killed_mid_run", killed},
                                   {"finished_before_kill", finished_first},
                                   {"stores_with_an_index_after_kill", published_count},
                                   {"stores_loaded_after_kill", loads},
                                   {"stores_unpainted_after_kill", unpainted},
                                   {"resumed", resumed},
                                   {"worst_placement_difference_px", worst_px},
                                   {"readers", config.readers},
                                   {"reader_full_reads", total_reads},
                                   {"reader_errors", total_problems},
                                   {"campaign_s", campaign_s},
                                   {"failures", failures}};
    std::ofstream(config.json) << report.dump(2) << "\n";
  }
  return failures == 0 ? 0 : 1;
}

}  // namespace
}  // namespace irmosaic

int main(int argc, char** argv) {
  irmosaic::Config config;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string key = argv[i], value = argv[i + 1];
    if (key == "--cli")
      config.cli = value;
    else if (key == "--plugin-dir")
      config.plugin_dir = value;
    else if (key == "--work")
      config.work = value;
    else if (key == "--json")
      config.json = value;
    else if (key == "--runs")
      config.runs = std::stoi(value);
    else if (key == "--readers")
      config.readers = std::stoi(value);
    else if (key == "--frames")
      config.frames = std::stoi(value);
    else if (key == "--seed")
      config.seed = std::stoull(value);
    else if (key == "--window")
      config.window = std::stoi(value);
    else if (key == "--short-window")
      config.short_window = std::stoi(value);
    else {
      std::cerr << "fault_campaign: unknown option " << key << "\n";
      return 2;
    }
  }
  if (config.cli.empty() || config.plugin_dir.empty() || config.work.empty()) {
    std::cerr << "usage: fault_campaign --cli IRMOSAIC --plugin-dir DIR --work DIR [--runs 20] "
                 "[--readers 4] [--frames 40] [--window 16] [--short-window 8] [--seed 11] "
                 "[--json FILE]\n";
    return 2;
  }
  try {
    return irmosaic::Main(config);
  } catch (const std::exception& e) {
    std::cerr << "fault_campaign: " << e.what() << "\n";
    return 2;
  }
}
