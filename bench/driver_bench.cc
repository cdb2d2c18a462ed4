// driver_bench: the IRMOSAIC GDAL driver against the store's mosaic.vrt on a large store.
//
// Builds (once; kept with --keep) a store of about --tiles level-0 tiles of 256 x 256 UInt16
// through TileStore (ZSTD, overviews grown with the extent), then, in the same run and for each
// of the two ways in, times: opening the store (manifest or VRT parse), reading a 1024 x 1024
// window of both bands at full resolution in the middle of the mosaic, and reading a
// 1024 x 1024 window of overview 2 (1/4 resolution, 4096 x 4096 level-0 pixels of ground), each
// from a fresh open (no block cache carried over), repeated --repeats times (median reported).
// Times are wall-clock and this thread's CPU time (CLOCK_THREAD_CPUTIME_ID, little inflated by
// other load on a shared machine). The driver is this build's, registered in-process before
// GDAL loads plug-ins (the same code as gdal_IRMOSAIC.so). Prints a table and writes JSON.
//
//   driver_bench [--tiles N] [--repeats N] [--dir DIR] [--keep] [--json FILE]
#include <gdal_priv.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iomanip>
#include <iostream>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "irmosaic/local_frame.h"
#include "irmosaic/tile_store.h"
#include "irmosaic_driver.h"

namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;
constexpr int kTile = 256;
constexpr double kLat0 = 47.2, kLon0 = 8.5, kGsd = 0.2;

double ThreadCpuMs() {
  timespec t{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return t.tv_sec * 1e3 + t.tv_nsec * 1e-6;
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

// What a small change costs to publish once the store is large: RequestPublish -> on disk for a
// 16 x 16 patch in one tile (its tile, its overview parents and the index), median of 5; and of
// that, the writer's time and bytes for the index (VRTs that changed, mosaic.vrt, manifest.json),
// mean of the 5; and the writer thread's CPU time per publish (little inflated by other load on
// a shared machine, unlike the wall times), mean of the 5.
double g_small_publish_ms = 0.0;
double g_small_writer_cpu_ms = 0.0;
double g_small_index_ms = 0.0;
double g_small_index_bytes = 0.0;

// A square store of side ceil(sqrt(tiles)) tiles, painted one tile row at a time (a publish per
// row keeps the writer's dirty set small). Returns the seconds it took.
double BuildStore(const fs::path& dir, int tiles) {
  const int side = static_cast<int>(std::ceil(std::sqrt(static_cast<double>(tiles))));
  irmosaic::TileStoreOptions options;
  options.path = dir.string();
  options.mode = irmosaic::TileStoreOptions::Mode::kOverwrite;
  options.tile_size = kTile;
  options.writer_nice = 0;
  const irmosaic::LocalFrame frame(kLat0, kLon0);
  const auto start = Clock::now();
  auto store = irmosaic::TileStore::Open(options, {kLat0, kLon0, kGsd, frame.CrsWkt()});
  const int width = side * kTile;
  cv::Mat strip(kTile, width, CV_16U), weight(kTile, width, CV_32F, cv::Scalar(1.0));
  for (int row = 0; row < side; ++row) {
    // Smooth thermal structure plus a fine texture (compresses like real IR, ~10:1 with ZSTD).
    for (int y = 0; y < kTile; ++y) {
      auto* p = strip.ptr<uint16_t>(y);
      const int gy = row * kTile + y;
      for (int x = 0; x < width; ++x) {
        p[x] = static_cast<uint16_t>(7500 + 250 * std::sin(x / 110.0) * std::cos(gy / 90.0) +
                                     0.05 * x + ((x * 7 + gy * 13) % 17));
      }
    }
    store->Paint(strip, weight, {0, row * kTile});
    store->RequestPublish();
  }
  store->WaitPublished(store->RequestPublish());
  const double build_s = std::chrono::duration<double>(Clock::now() - start).count();
  std::vector<double> small;
  const irmosaic::TileStore::Stats before = store->stats();
  for (int i = 0; i < 5; ++i) {
    const cv::Mat patch(16, 16, CV_16U, cv::Scalar(9000 + i)), w(16, 16, CV_32F, cv::Scalar(1.0));
    store->Paint(patch, w, {width / 2 + 32 * i, width / 2});
    const auto t0 = Clock::now();
    store->WaitPublished(store->RequestPublish());
    small.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
  }
  g_small_publish_ms = Median(small);
  const irmosaic::TileStore::Stats after = store->stats();
  g_small_writer_cpu_ms = (after.writer_cpu_ms - before.writer_cpu_ms) / 5;
  g_small_index_ms = (after.index_ms_total - before.index_ms_total) / 5;
  g_small_index_bytes = static_cast<double>(after.index_bytes_total - before.index_bytes_total) / 5;
  store->Close();
  return build_s;
}

struct Timing {
  double wall_ms = 0, cpu_ms = 0;
};

// Median wall and thread-CPU time of `run` over `repeats` calls.
Timing Time(int repeats, const std::function<void()>& run) {
  std::vector<double> wall, cpu;
  for (int i = 0; i < repeats; ++i) {
    const auto start = Clock::now();
    const double cpu0 = ThreadCpuMs();
    run();
    cpu.push_back(ThreadCpuMs() - cpu0);
    wall.push_back(std::chrono::duration<double, std::milli>(Clock::now() - start).count());
  }
  return {Median(wall), Median(cpu)};
}

GDALDataset* OpenWith(const fs::path& path, const char* driver) {
  const char* const allowed[] = {driver, nullptr};
  return GDALDataset::Open(path.c_str(), GDAL_OF_RASTER | GDAL_OF_READONLY, allowed, nullptr,
                           nullptr);
}

// Reads a 1024 x 1024 window of both bands of `ds` at full resolution (overview < 0) or of
// overview `overview`, centred; returns the sum of band 1 (to compare the two ways in).
double ReadWindow(GDALDataset* ds, int overview, std::vector<uint16_t>* buffer) {
  double sum = 0;
  for (int b = 1; b <= 2; ++b) {
    GDALRasterBand* band = ds->GetRasterBand(b);
    if (overview >= 0) band = band->GetOverview(overview);
    if (band == nullptr) throw std::runtime_error("missing overview");
    const int w = std::min(1024, band->GetXSize()), h = std::min(1024, band->GetYSize());
    const int x = (band->GetXSize() - w) / 2, y = (band->GetYSize() - h) / 2;
    if (band->RasterIO(GF_Read, x, y, w, h, buffer->data(), w, h, GDT_UInt16, 0, 0, nullptr) !=
        CE_None) {
      throw std::runtime_error(std::string("read failed: ") + CPLGetLastErrorMsg());
    }
    if (b == 1) {
      for (int i = 0; i < w * h; ++i) sum += (*buffer)[i];
    }
  }
  return sum;
}

// Tiles a manifest level lists: one entry each in format 1, the set bits of its blocks' bitmaps
// (64 hex digits) in format 2.
size_t LevelTileCount(const nlohmann::json& level) {
  if (level.contains("tiles")) return level["tiles"].size();
  size_t count = 0;
  for (const auto& block : level["blocks"]) {
    for (const char digit : block[2].get<std::string>()) {
      count += std::popcount(static_cast<unsigned>(std::stoi(std::string(1, digit), nullptr, 16)));
    }
  }
  return count;
}

struct Row {
  std::string way, what;
  Timing timing;
  double sum = 0;
};

}  // namespace

int main(int argc, char** argv) {
  int tiles = 10000, repeats = 5;
  bool keep = false;
  std::string json_path;
  fs::path dir = fs::temp_directory_path() / "driver_bench.irmosaic";
  for (int i = 1; i < argc; ++i) {
    const std::string key = argv[i];
    const bool has_value = i + 1 < argc;
    if (key == "--keep") {
      keep = true;
    } else if (key == "--tiles" && has_value) {
      tiles = std::stoi(argv[++i]);
    } else if (key == "--repeats" && has_value) {
      repeats = std::stoi(argv[++i]);
    } else if (key == "--dir" && has_value) {
      dir = argv[++i];
    } else if (key == "--json" && has_value) {
      json_path = argv[++i];
    } else {
      std::cerr << "usage: driver_bench [--tiles N] [--repeats N] [--dir DIR] [--keep]"
                   " [--json FILE]\n";
      return 2;
    }
  }
  // This build's driver first, so an installed gdal_IRMOSAIC.so does not take the name.
  GDALRegister_IRMOSAIC();
  GDALAllRegister();

  double build_s = 0;
  const fs::path manifest = dir / "manifest.json";
  if (!keep || !fs::exists(manifest)) build_s = BuildStore(dir, tiles);
  std::ifstream in(manifest);
  const nlohmann::json m = nlohmann::json::parse(in);
  const uintmax_t vrt_bytes = fs::file_size(dir / "mosaic.vrt");
  const uintmax_t manifest_bytes = fs::file_size(manifest);
  const size_t level0_tiles = LevelTileCount(m["levels"][0]);
  size_t all_tiles = 0;
  for (const auto& level : m["levels"]) all_tiles += LevelTileCount(level);
  uintmax_t bytes = 0;
  for (const auto& entry : fs::recursive_directory_iterator(dir)) {
    if (entry.is_regular_file()) bytes += entry.file_size();
  }

  std::vector<uint16_t> buffer(1024 * 1024);
  std::vector<Row> rows;
  int width = 0, height = 0, overviews = 0;
  for (const auto& [way, path, driver] : {std::tuple{"IRMOSAIC", dir, "IRMOSAIC"},
                                          std::tuple{"mosaic.vrt", dir / "mosaic.vrt", "VRT"}}) {
    rows.push_back({way, "open", Time(repeats, [&, p = path, d = driver] {
                      GDALDatasetUniquePtr ds(OpenWith(p, d));
                      if (!ds) throw std::runtime_error("cannot open " + p.string());
                      width = ds->GetRasterXSize();
                      height = ds->GetRasterYSize();
                      overviews = ds->GetRasterBand(1)->GetOverviewCount();
                    })});
    for (const auto& [what, overview] : {std::pair{"open + read 1024^2 full res", -1},
                                         std::pair{"open + read 1024^2 overview 2", 1}}) {
      double sum = 0;
      const Timing t = Time(repeats, [&, p = path, d = driver, o = overview] {
        GDALDatasetUniquePtr ds(OpenWith(p, d));
        sum = ReadWindow(ds.get(), o, &buffer);
      });
      rows.push_back({way, what, t, sum});
    }
  }
  if (!keep) fs::remove_all(dir);

  std::cout << "driver_bench: store of " << level0_tiles << " level-0 tiles (" << all_tiles
            << " with overviews) of " << kTile << " px UInt16 ZSTD, " << width << " x " << height
            << " px, " << overviews << " overviews, " << bytes / (1 << 20) << " MiB"
            << (build_s > 0 ? ", built in " + std::to_string(static_cast<int>(build_s)) + " s"
                            : std::string(", reused"))
            << "; median of " << repeats << " fresh opens, page cache warm\n";
  if (build_s > 0) {
    std::cout << "publishing a 16 x 16 patch at this size: " << std::fixed << std::setprecision(1)
              << g_small_publish_ms << " ms (median of 5), writer CPU " << g_small_writer_cpu_ms
              << " ms, of which the index " << g_small_index_ms << " ms, "
              << g_small_index_bytes / 1024 << " KiB (mean); mosaic.vrt " << vrt_bytes / 1024
              << " KiB, manifest.json " << manifest_bytes / 1024 << " KiB\n";
  }
  std::cout << "\n";
  std::cout << std::left << std::setw(12) << "way in" << std::setw(32) << "what" << std::right
            << std::setw(10) << "wall ms" << std::setw(10) << "cpu ms" << std::setw(16)
            << "band-1 sum\n";
  nlohmann::json results = nlohmann::json::array();
  for (const Row& r : rows) {
    std::cout << std::left << std::setw(12) << r.way << std::setw(32) << r.what << std::right
              << std::fixed << std::setprecision(1) << std::setw(10) << r.timing.wall_ms
              << std::setw(10) << r.timing.cpu_ms << std::setw(15) << std::setprecision(0) << r.sum
              << "\n";
    results.push_back({{"way", r.way},
                       {"what", r.what},
                       {"wall_ms_median", r.timing.wall_ms},
                       {"thread_cpu_ms_median", r.timing.cpu_ms},
                       {"band1_sum", r.sum}});
  }
  if (!json_path.empty()) {
    std::ofstream(json_path) << nlohmann::json{{"benchmark", "driver_bench"},
                                               {"level0_tiles", level0_tiles},
                                               {"tiles_all_levels", all_tiles},
                                               {"tile_size", kTile},
                                               {"width_px", width},
                                               {"height_px", height},
                                               {"overviews", overviews},
                                               {"store_bytes", bytes},
                                               {"build_s", build_s},
                                               {"small_publish_ms", g_small_publish_ms},
                                               {"small_publish_writer_cpu_ms",
                                                g_small_writer_cpu_ms},
                                               {"small_publish_index_ms", g_small_index_ms},
                                               {"small_publish_index_bytes", g_small_index_bytes},
                                               {"mosaic_vrt_bytes", vrt_bytes},
                                               {"manifest_bytes", manifest_bytes},
                                               {"repeats", repeats},
                                               {"results", results}}
                                    .dump(2)
                             << "\n";
  }
  return 0;
}
