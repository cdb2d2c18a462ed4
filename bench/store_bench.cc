// store_bench: cost of the live output per frame, as a flight feeds it.
//
// A simulated sweeping flight paints 640x512 UInt16 patches (feathered weights, sensor noise) and
// puts one footprint record per frame at 25 frames/s into a TileStore and publishes every
// --publish_every frames, with the writer on its own thread. For each compression it reports the
// calling thread's cost per frame (Paint), the writer's work per frame (amortised), publish
// latency, frame arrival -> published latency, and the store's size per frame. Prints a table and
// writes JSON (--json FILE). Then the cost of publishing 25 new footprints into frames.gpkg
// holding 1,000, 15,000 and 90,000 (an hour) records, and the CPU of the writer's unit of work on
// one thread: one level-0 tile written, read back and halved, and the writer's CPU for a publish
// adding one tile to a store of 1,000 / 10,000 / 40,000 tiles, and the writer's CPU and index
// bytes of a publish repainting one tile of a store of 100 / 1,000 / 4,000 blocks.
// --frames 0 runs only those parts.
// With --zstd-tiles DIR (a store's tiles/0 folder, e.g. one flight_bench --store left), the
// compressor's settings on those real tiles instead: CPU per tile to apply the predictor and
// compress the data band's 256 x 256 blocks, to decompress them, and the bytes, for zstd level 1
// (the store's), 3, smaller match tables, and negative levels with and without their literals
// entropy-coded (libzstd's experimental ZSTD_c_literalCompressionMode).
//
//   store_bench [--frames N] [--publish_every N] [--fps F] [--json FILE] [--dir DIR]
//               [--zstd-tiles DIR]
#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <mutex>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <string>
#include <thread>
#include <vector>

#define ZSTD_STATIC_LINKING_ONLY  // ZSTD_c_literalCompressionMode (experimental).
#include <gdal.h>
#include <zstd.h>

#include "../src/feather_weight.h"
#include "../src/simd_dispatch.h"
#include "../src/store_internal.h"
#include "irmosaic/local_frame.h"
#include "irmosaic/tile_store.h"

namespace {

namespace fs = std::filesystem;
using Clock = std::chrono::steady_clock;

double Ms(Clock::duration d) { return std::chrono::duration<double, std::milli>(d).count(); }

double Percentile(std::vector<double> values, double q) {
  if (values.empty()) return 0.0;
  std::sort(values.begin(), values.end());
  const size_t i = std::min(
      values.size() - 1,
      static_cast<size_t>(std::ceil(q * static_cast<double>(values.size()))) - (q > 0 ? 1 : 0));
  return values[i];
}

// The ground the flight sees: smooth thermal structure, warm blobs and sensor noise (16-bit).
cv::Mat MakeGround(int size) {
  cv::Mat ground(size, size, CV_16U);
  std::mt19937 random(7);
  std::normal_distribution<float> noise(0.0f, 12.0f);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const double smooth = 7500 + 250 * std::sin(x / 110.0) * std::cos(y / 90.0) + 0.2 * x;
      const double blob = std::exp(
          -(std::pow(std::fmod(x, 350.0) - 175, 2) + std::pow(std::fmod(y, 410.0) - 205, 2)) /
          900.0);
      ground.at<uint16_t>(y, x) = cv::saturate_cast<uint16_t>(smooth + 900 * blob + noise(random));
    }
  }
  return ground;
}

cv::Mat Feather(cv::Size size) {
  cv::Mat weight(size, CV_32F);
  for (int y = 0; y < size.height; ++y) {
    for (int x = 0; x < size.width; ++x) {
      const int d = std::min({x, y, size.width - 1 - x, size.height - 1 - y});
      weight.at<float>(y, x) = std::min(1.0f, (d + 1) / 24.0f);
    }
  }
  return weight;
}

struct Result {
  std::string compression;
  int frames = 0;
  double paint_mean_ms = 0, paint_p99_ms = 0, paint_max_ms = 0;
  double writer_ms_per_frame = 0;
  double publish_p50_ms = 0, publish_p99_ms = 0, publish_max_ms = 0;
  double frame_to_published_p50_ms = 0, frame_to_published_p99_ms = 0,
         frame_to_published_max_ms = 0;
  double store_kb_per_frame = 0, written_kb_per_frame = 0;
  int64_t tiles_written = 0, publishes = 0;
  double wall_s = 0;
};

Result RunFlight(const std::string& compression, int level, const cv::Mat& ground, int frames,
                 int publish_every, double fps, const fs::path& dir) {
  fs::remove_all(dir);
  const irmosaic::LocalFrame frame(47.2, 8.5);
  irmosaic::TileStoreOptions options;
  options.path = dir.string();
  options.compression = compression;
  options.compression_level = level;
  auto store = irmosaic::TileStore::Open(options, {47.2, 8.5, 0.5, frame.CrsWkt()});
  const cv::Size patch(640, 512);
  const cv::Mat weight = Feather(patch);

  // Publication times, watched from another thread (what a reader would experience).
  std::mutex mutex;
  std::vector<Clock::time_point> published_at(frames / publish_every + 4, Clock::time_point{});
  std::thread watcher([&] {
    for (int64_t g = 1; g < static_cast<int64_t>(published_at.size()); ++g) {
      try {
        store->WaitPublished(g);
      } catch (...) {
        return;
      }
      std::lock_guard<std::mutex> lock(mutex);
      published_at[g] = Clock::now();
    }
  });

  std::vector<double> paint_ms;
  std::vector<std::pair<Clock::time_point, int64_t>> arrivals;  // (painted, generation)
  const auto start = Clock::now();
  int64_t generation = 0;
  for (int i = 0; i < frames; ++i) {
    // Oblique sweep: across-track +-1100 px with a 2 s period, along-track 20 px/s.
    const double t = i / fps;
    const int cx = static_cast<int>(ground.cols / 2 + 1100 * std::sin(2 * M_PI * t / 2.0));
    const int cy = static_cast<int>(ground.rows - 600 - 20 * t);
    const cv::Rect roi(cx - patch.width / 2, cy - patch.height / 2, patch.width, patch.height);
    const cv::Mat image = ground(roi);
    const auto before = Clock::now();
    const cv::Point origin = roi.tl() - cv::Point(ground.cols / 2, ground.rows / 2);
    store->Paint(image, weight, origin);
    irmosaic::FrameRecord record;  // As `run` would: one footprint per frame into frames.gpkg.
    record.index = i;
    record.time_s = t;
    const double x0 = origin.x * 0.5, y0 = -origin.y * 0.5;
    record.footprint_m = {
        Eigen::Vector2d(x0, y0), {x0 + 320, y0}, {x0 + 320, y0 - 256}, {x0, y0 - 256}};
    record.inliers = 150;
    record.residual_px = 0.4;
    record.status = "registered";
    store->PutFrameRecord(record);
    if ((i + 1) % publish_every == 0) generation = store->RequestPublish();
    const auto after = Clock::now();
    paint_ms.push_back(Ms(after - before));
    arrivals.emplace_back(after, (i + 1) % publish_every == 0 ? generation : generation + 1);
    std::this_thread::sleep_until(start + std::chrono::duration_cast<Clock::duration>(
                                              std::chrono::duration<double>((i + 1) / fps)));
  }
  generation = store->RequestPublish();
  store->WaitPublished(generation);
  const double wall_s = Ms(Clock::now() - start) / 1000.0;
  store->Close();
  watcher.join();

  const irmosaic::TileStore::Stats stats = store->stats();
  Result r;
  r.compression = compression + (compression == "NONE" ? "" : " " + std::to_string(level));
  r.frames = frames;
  double sum = 0;
  for (double v : paint_ms) sum += v;
  r.paint_mean_ms = sum / frames;
  r.paint_p99_ms = Percentile(paint_ms, 0.99);
  r.paint_max_ms = Percentile(paint_ms, 1.0);
  r.writer_ms_per_frame = stats.writer_busy_ms / frames;
  r.publish_p50_ms = stats.publish_p50_ms;
  r.publish_p99_ms = stats.publish_p99_ms;
  r.publish_max_ms = stats.publish_max_ms;
  std::vector<double> latency;
  for (const auto& [painted, g] : arrivals) {
    const int64_t gen = std::min<int64_t>(g, static_cast<int64_t>(published_at.size()) - 1);
    // The final publish (Close) may fall outside the watched range: skip those few frames.
    if (published_at[gen] != Clock::time_point{})
      latency.push_back(Ms(published_at[gen] - painted));
  }
  r.frame_to_published_p50_ms = Percentile(latency, 0.5);
  r.frame_to_published_p99_ms = Percentile(latency, 0.99);
  r.frame_to_published_max_ms = Percentile(latency, 1.0);
  int64_t store_bytes = 0;
  for (const auto& entry : fs::recursive_directory_iterator(dir)) {
    if (entry.is_regular_file()) store_bytes += static_cast<int64_t>(entry.file_size());
  }
  r.store_kb_per_frame = store_bytes / 1024.0 / frames;
  r.written_kb_per_frame = stats.bytes_written / 1024.0 / frames;
  r.tiles_written = stats.tiles_written;
  r.publishes = stats.publishes;
  r.wall_s = wall_s;
  return r;
}

// Publish time of 25 changed frame records when frames.gpkg already holds `existing` records
// (the file is copied, updated and renamed on each such publish). Median of 5 publishes.
double FramesPublishMs(int existing, const fs::path& dir) {
  fs::remove_all(dir);
  const irmosaic::LocalFrame frame(47.2, 8.5);
  irmosaic::TileStoreOptions options;
  options.path = dir.string();
  auto store = irmosaic::TileStore::Open(options, {47.2, 8.5, 0.5, frame.CrsWkt()});
  const auto put = [&](int index) {
    irmosaic::FrameRecord record;
    record.index = index;
    record.time_s = index / 25.0;
    record.footprint_m = {
        Eigen::Vector2d(index, 0), {index + 320.0, 0}, {index + 320.0, -256}, {index, -256}};
    record.status = "registered";
    store->PutFrameRecord(record);
  };
  for (int i = 0; i < existing; ++i) put(i);
  store->WaitPublished(store->RequestPublish());
  std::vector<double> ms;
  for (int round = 0; round < 5; ++round) {
    for (int i = 0; i < 25; ++i) put(existing + round * 25 + i);
    const auto start = Clock::now();
    store->WaitPublished(store->RequestPublish());
    ms.push_back(Ms(Clock::now() - start));
  }
  store->Close();
  fs::remove_all(dir);
  return Percentile(ms, 0.5);
}

// A fresh store of 64-pixel Byte tiles at `dir` (a large store builds in seconds), overviews by
// the clock and not due for an hour: what the index measurements below publish into.
std::unique_ptr<irmosaic::TileStore> OpenIndexStore(const fs::path& dir) {
  fs::remove_all(dir);
  const irmosaic::LocalFrame frame(47.2, 8.5);
  irmosaic::TileStoreOptions options;
  options.path = dir.string();
  options.tile_size = 64;
  options.pixel_type = irmosaic::PixelType::kByte;
  options.overview_interval_s = 3600.0;
  return irmosaic::TileStore::Open(options, {47.2, 8.5, 0.5, frame.CrsWkt()});
}

// Writer CPU (ms) of a publish that adds one level-0 tile to a store already holding `existing`
// ones: the part of a publish that grows with the flight (the index: manifest.json, the VRTs,
// the writer's tile lists). 64-pixel Byte tiles so that a large store builds in seconds; overviews
// by the clock, not due during the measured publishes. Median of 9.
double IndexPublishMs(int existing, const fs::path& dir) {
  auto store = OpenIndexStore(dir);
  const int per_row = 250;
  const cv::Mat strip(64, 64 * per_row, CV_8U, cv::Scalar(100));
  const cv::Mat strip_weight(strip.size(), CV_32F, cv::Scalar(1.0f));
  for (int row = 0; row * per_row < existing; ++row) {
    const int cols = std::min(per_row, existing - row * per_row);
    store->Paint(strip(cv::Rect(0, 0, 64 * cols, 64)), strip_weight(cv::Rect(0, 0, 64 * cols, 64)),
                 {0, 64 * row});
    if (row % 8 == 7) store->WaitPublished(store->RequestPublish());
  }
  store->WaitPublished(store->RequestPublish());
  const cv::Mat tile(64, 64, CV_8U, cv::Scalar(150));
  const cv::Mat tile_weight(64, 64, CV_32F, cv::Scalar(1.0f));
  std::vector<double> ms;
  for (int k = 0; k < 9; ++k) {
    store->Paint(tile, tile_weight, {-64 * (k + 1), -64});
    const double before = store->stats().writer_cpu_ms;
    store->WaitPublished(store->RequestPublish());
    ms.push_back(store->stats().writer_cpu_ms - before);
  }
  store->Close();
  fs::remove_all(dir);
  return Percentile(ms, 0.5);
}

// A publish that repaints one tile of a store whose level-0 tiles lie one per block of 16 x 16
// (`blocks` of them: a flight's sparse edges, which make many blocks), as most publishes of a
// flight do (tiles inside existing blocks): the writer's CPU ms and the index bytes it writes,
// medians of 9. The index files that do not change are not rewritten; mosaic.vrt and
// manifest.json are, at every publish.
struct RepaintIndexCost {
  double writer_cpu_ms = 0;
  double index_kib = 0;
};

RepaintIndexCost RepaintIndexPublish(int blocks, const fs::path& dir) {
  auto store = OpenIndexStore(dir);
  const cv::Mat tile(64, 64, CV_8U, cv::Scalar(100));
  const cv::Mat weight(64, 64, CV_32F, cv::Scalar(1.0f));
  const int across = static_cast<int>(std::ceil(std::sqrt(static_cast<double>(blocks))));
  const auto at = [&](int k) { return cv::Point(64 * 16 * (k % across), 64 * 16 * (k / across)); };
  for (int k = 0; k < blocks; ++k) {
    store->Paint(tile, weight, at(k));
    if (k % 256 == 255) store->WaitPublished(store->RequestPublish());
  }
  store->WaitPublished(store->RequestPublish());
  std::vector<double> ms, kib;
  for (int k = 0; k < 9; ++k) {
    store->Paint(tile, weight, at(k));
    const irmosaic::TileStore::Stats before = store->stats();
    store->WaitPublished(store->RequestPublish());
    const irmosaic::TileStore::Stats after = store->stats();
    ms.push_back(after.writer_cpu_ms - before.writer_cpu_ms);
    kib.push_back(static_cast<double>(after.index_bytes_total - before.index_bytes_total) / 1024);
  }
  store->Close();
  fs::remove_all(dir);
  return {Percentile(ms, 0.5), Percentile(kib, 0.5)};
}

double ThreadCpuMs() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec / 1e6;
}

// The writer's unit of work, one 512 x 512 UInt16 level-0 tile (cut from the ground, fully
// covered), on this thread: written to its GeoTIFF (ZSTD 1, the default) and renamed, read back,
// halved for the overview above (into pooled buffers, as the writer does). CPU ms per tile, the
// minimum over `rounds` rounds of `count` operations each (the VM's timing noise).
struct TileCost {
  double write_ms = 0, write_gdal_ms = 0, read_ms = 0, read_gdal_ms = 0, halve_ms = 0,
         halve_edge_ms = 0, write_one_block_ms = 0, write_edge_ms = 0;
  int64_t bytes = 0, gdal_bytes = 0;
};

TileCost MeasureTileCost(const cv::Mat& ground, irmosaic::PixelType type, int count, int rounds,
                         const fs::path& dir) {
  namespace st = irmosaic::store;
  fs::remove_all(dir);
  fs::create_directories(dir);
  const irmosaic::LocalFrame frame(47.2, 8.5);
  st::TileWriteSettings settings;
  settings.crs_wkt = frame.CrsWkt();
  settings.type = type;
  const int size = 512;
  st::TileImage tile = st::EmptyTile(size, type);
  if (type == irmosaic::PixelType::kUInt16) {
    ground(cv::Rect(1000, 1000, size, size)).copyTo(tile.data);
  } else {  // The patch's range stretched over 8 bits.
    cv::normalize(ground(cv::Rect(1000, 1000, size, size)), tile.data, 0, 255, cv::NORM_MINMAX,
                  CV_8U);
  }
  tile.alpha.setTo(255);
  double gt[6];
  st::TileGeoTransform(0.5, size, 0, {1, 2}, gt);
  st::TilePools pools(size, type, 4);  // As the writer halves.
  TileCost best{1e30, 1e30, 1e30, 1e30, 1e30, 1e30, 1e30, 1e30, 0, 0};
  // A tile at the mosaic's edge: a footprint's straight border across it, covered on one side.
  st::TileImage edge{tile.data.clone(), cv::Mat::zeros(size, size, CV_8U)};
  const std::vector<cv::Point> covered = {{0, 0}, {size, 0}, {size, size / 3}, {0, size}};
  cv::fillConvexPoly(edge.alpha, covered, cv::Scalar(255));
  edge.data.setTo(0, edge.alpha == 0);
  const fs::path path = dir / "tile.tif";
  for (int round = 0; round < rounds; ++round) {
    double t0 = ThreadCpuMs();
    for (int k = 0; k < count; ++k) best.bytes = st::WriteTileAtomic(path, tile, gt, settings);
    best.write_ms = std::min(best.write_ms, (ThreadCpuMs() - t0) / count);
    // The same tile through GDAL's GTiff driver (the encoder before session 36).
    st::TileWriteSettings by_gdal = settings;
    by_gdal.encoding = st::TileEncoding::kGdal;
    t0 = ThreadCpuMs();
    for (int k = 0; k < count; ++k) best.gdal_bytes = st::WriteTileAtomic(path, tile, gt, by_gdal);
    best.write_gdal_ms = std::min(best.write_gdal_ms, (ThreadCpuMs() - t0) / count);
    // Written again with one of its four blocks changed: the other three copied from its file.
    st::TileFileLayout layout;
    st::WriteTileAtomic(path, tile, gt, settings, nullptr, &layout);
    t0 = ThreadCpuMs();
    for (int k = 0; k < count; ++k) {
      const st::TileReuse reuse{&layout, st::BlockMask{1}};
      st::TileFileLayout next;
      st::WriteTileAtomic(path, tile, gt, settings, &reuse, &next);
      layout = std::move(next);
    }
    best.write_one_block_ms = std::min(best.write_one_block_ms, (ThreadCpuMs() - t0) / count);
    // The edge tile (a third uncovered: blocks of one value in both bands).
    t0 = ThreadCpuMs();
    for (int k = 0; k < count; ++k) st::WriteTileAtomic(path, edge, gt, settings);
    best.write_edge_ms = std::min(best.write_edge_ms, (ThreadCpuMs() - t0) / count);
    st::WriteTileAtomic(path, tile, gt, settings);  // What the reads below read.
    t0 = ThreadCpuMs();
    for (int k = 0; k < count; ++k) st::ReadTile(path, size, type);
    best.read_ms = std::min(best.read_ms, (ThreadCpuMs() - t0) / count);
    t0 = ThreadCpuMs();
    for (int k = 0; k < count; ++k) {
      st::ReadTile(path, size, type, nullptr, st::TileDecoding::kGdal);
    }
    best.read_gdal_ms = std::min(best.read_gdal_ms, (ThreadCpuMs() - t0) / count);
    t0 = ThreadCpuMs();
    for (int k = 0; k < count; ++k) st::HalveTile(tile, &pools);
    best.halve_ms = std::min(best.halve_ms, (ThreadCpuMs() - t0) / count);
    t0 = ThreadCpuMs();
    for (int k = 0; k < count; ++k) st::HalveTile(edge, &pools);
    best.halve_edge_ms = std::min(best.halve_edge_ms, (ThreadCpuMs() - t0) / count);
  }
  fs::remove_all(dir);
  return best;
}

// TileStore::Paint's CPU for one patch over tiles already covered (the blend's work, no tile
// read back or created): the bounding box of an oblique, rotated footprint as a render paints it
// (1000 x 960 px, feathered weights over the footprint, 0 around it: about half the box), CPU ms
// on this thread, the minimum over 5 rounds of 30 paints; with AVX2 allowed and with SSE2 only.
struct PaintCost {
  double avx2_ms = 0, sse2_ms = 0;
};

PaintCost MeasurePaintCost(irmosaic::PixelType type, const fs::path& dir) {
  fs::remove_all(dir);
  const irmosaic::LocalFrame frame(47.2, 8.5);
  irmosaic::TileStoreOptions options;
  options.path = dir.string();
  options.pixel_type = type;
  auto store = irmosaic::TileStore::Open(options, {47.2, 8.5, 0.5, frame.CrsWkt()});
  const cv::Size size(1000, 960);
  const std::array<Eigen::Vector2d, 4> quad = {
      Eigen::Vector2d(180.0, 40.0), Eigen::Vector2d(960.0, 300.0), Eigen::Vector2d(700.0, 930.0),
      Eigen::Vector2d(60.0, 520.0)};
  std::array<cv::Point, 4> points;
  for (int k = 0; k < 4; ++k) points[k] = cv::Point(quad[k].x(), quad[k].y());
  cv::Mat mask(size, CV_8U, cv::Scalar(0)), weight;
  cv::fillConvexPoly(mask, points.data(), 4, cv::Scalar(255));
  irmosaic::feather::Weight(quad, 24.0, mask, &weight);
  const int depth = type == irmosaic::PixelType::kByte ? CV_8U : CV_16U;
  cv::Mat image(size, depth);
  cv::randu(image, 0, depth == CV_8U ? 256 : 65536);
  const cv::Point origin(-300, -200);
  store->Paint(image, cv::Mat(size, CV_32F, cv::Scalar(1.0f)), origin);  // Covered.
  PaintCost best{1e30, 1e30};
  for (int round = 0; round < 5; ++round) {
    for (const bool avx2 : {true, false}) {
      const bool before = irmosaic::simd::SetAvx2Allowed(avx2);
      const double t0 = ThreadCpuMs();
      for (int k = 0; k < 30; ++k) store->Paint(image, weight, origin);
      double& slot = avx2 ? best.avx2_ms : best.sse2_ms;
      slot = std::min(slot, (ThreadCpuMs() - t0) / 30);
      irmosaic::simd::SetAvx2Allowed(before);
    }
  }
  store.reset();
  fs::remove_all(dir);
  return best;
}

}  // namespace

// One setting of the compressor, as --zstd-tiles measures it.
struct ZstdSetting {
  std::string name;
  int level = 1;
  bool literals_coded = false;  // Force Huffman coding of literals (negative levels skip it).
  int hash_log = 0;             // 0: the level's own.
};

struct ZstdResult {
  ZstdSetting setting;
  double compress_ms = 0, decompress_ms = 0, kib_per_tile = 0, ratio = 0;
};

// The store's level-0 tiles under `tiles_dir` that are at least 90 % covered (what the writer
// encodes most), at most `count`, spread over the folder; their data band as 8 or 16 bits.
std::vector<cv::Mat> LoadCoveredTiles(const fs::path& tiles_dir, size_t count) {
  namespace st = irmosaic::store;
  std::vector<fs::path> paths;
  for (const auto& entry : fs::directory_iterator(tiles_dir)) {
    if (entry.path().extension() == ".tif") paths.push_back(entry.path());
  }
  std::sort(paths.begin(), paths.end());
  GDALAllRegister();  // ReadTile opens the tiles' headers through GDAL.
  std::vector<cv::Mat> tiles;
  const size_t step = std::max<size_t>(1, paths.size() / (4 * count));
  for (size_t i = 0; i < paths.size() && tiles.size() < count; i += step) {
    for (const auto type : {irmosaic::PixelType::kByte, irmosaic::PixelType::kUInt16}) {
      try {
        const st::TileImage tile = st::ReadTile(paths[i], 512, type);
        if (static_cast<size_t>(cv::countNonZero(tile.alpha == 255)) >=
            tile.alpha.total() * 9 / 10) {
          tiles.push_back(tile.data.clone());
        }
        break;
      } catch (const std::exception&) {  // Of the other type: try it.
      }
    }
  }
  return tiles;
}

std::vector<ZstdResult> MeasureZstdSettings(const std::vector<cv::Mat>& tiles) {
  namespace st = irmosaic::store;
  const std::vector<ZstdSetting> settings = {{"level 1 (the store's)", 1, false, 0},
                                             {"level 3", 3, false, 0},
                                             {"level 1, hashLog 10", 1, false, 10},
                                             {"level -1", -1, false, 0},
                                             {"level -5", -5, false, 0},
                                             {"level -1, literals coded", -1, true, 0},
                                             {"level -5, literals coded", -5, true, 0},
                                             {"level -50, literals coded", -50, true, 0}};
  std::unique_ptr<ZSTD_CCtx, size_t (*)(ZSTD_CCtx*)> compressor(ZSTD_createCCtx(), ZSTD_freeCCtx);
  std::unique_ptr<ZSTD_DCtx, size_t (*)(ZSTD_DCtx*)> decompressor(ZSTD_createDCtx(), ZSTD_freeDCtx);
  std::vector<ZstdResult> results;
  for (const ZstdSetting& setting : settings) {
    ZSTD_CCtx* c = compressor.get();
    ZSTD_CCtx_reset(c, ZSTD_reset_session_and_parameters);
    bool refused = ZSTD_isError(ZSTD_CCtx_setParameter(c, ZSTD_c_compressionLevel, setting.level));
    if (setting.literals_coded) {
      refused |=
          ZSTD_isError(ZSTD_CCtx_setParameter(c, ZSTD_c_literalCompressionMode, ZSTD_ps_enable));
    }
    if (setting.hash_log > 0) {
      refused |= ZSTD_isError(ZSTD_CCtx_setParameter(c, ZSTD_c_hashLog, setting.hash_log));
    }
    if (refused) {
      std::cerr << "store_bench: libzstd refused the setting " << setting.name << "\n";
      continue;
    }
    ZstdResult r{setting};
    r.compress_ms = r.decompress_ms = 1e30;
    for (int round = 0; round < 5; ++round) {
      double compress = 0, decompress = 0, bytes = 0, raw_bytes = 0;
      for (const cv::Mat& tile : tiles) {
        const size_t sample = tile.elemSize();
        const size_t block_bytes = 256 * 256 * sample;
        std::vector<uint8_t> raw(block_bytes), back(block_bytes),
            packed(ZSTD_compressBound(block_bytes));
        for (int y0 = 0; y0 < tile.rows; y0 += 256) {
          for (int x0 = 0; x0 < tile.cols; x0 += 256) {
            double t0 = ThreadCpuMs();
            for (int row = 0; row < 256; ++row) {
              if (sample == 1) {
                st::HorizontalDifferencing(tile.ptr<uint8_t>(y0 + row) + x0,
                                           raw.data() + static_cast<size_t>(row) * 256, 256);
              } else {
                st::HorizontalDifferencing(
                    tile.ptr<uint16_t>(y0 + row) + x0,
                    reinterpret_cast<uint16_t*>(raw.data()) + static_cast<size_t>(row) * 256, 256);
              }
            }
            const size_t n =
                ZSTD_compress2(c, packed.data(), packed.size(), raw.data(), block_bytes);
            double t1 = ThreadCpuMs();
            compress += t1 - t0;
            if (ZSTD_isError(n)) throw std::runtime_error(ZSTD_getErrorName(n));
            const size_t m =
                ZSTD_decompressDCtx(decompressor.get(), back.data(), back.size(), packed.data(), n);
            decompress += ThreadCpuMs() - t1;
            if (ZSTD_isError(m) || back != raw) throw std::runtime_error("zstd round trip");
            bytes += static_cast<double>(n);
            raw_bytes += static_cast<double>(block_bytes);
          }
        }
      }
      const double count = static_cast<double>(tiles.size());
      r.compress_ms = std::min(r.compress_ms, compress / count);
      r.decompress_ms = std::min(r.decompress_ms, decompress / count);
      r.kib_per_tile = bytes / 1024.0 / count;
      r.ratio = bytes / raw_bytes;
    }
    results.push_back(r);
  }
  return results;
}

int RunZstdSettings(const fs::path& tiles_dir, const std::string& json_path) {
  const std::vector<cv::Mat> tiles = LoadCoveredTiles(tiles_dir, 200);
  if (tiles.empty()) {
    std::cerr << "store_bench: --zstd-tiles " << tiles_dir
              << ": no level-0 tile at least 90 % covered there; give a store's tiles/0 folder\n";
    return 1;
  }
  const std::vector<ZstdResult> results = MeasureZstdSettings(tiles);
  std::cout << "store_bench: zstd settings on " << tiles.size() << " covered 512 x 512 tiles of "
            << tiles_dir.string() << " (" << (tiles[0].elemSize() == 1 ? "Byte" : "UInt16")
            << "; data band, predictor 2, 256 x 256 blocks; CPU ms per tile, minimum of 5 rounds; "
               "libzstd "
            << ZSTD_versionString() << ")\n\n";
  std::cout << std::left << std::setw(28) << "setting" << std::right << std::setw(14)
            << "compress ms" << std::setw(15) << "decompress ms" << std::setw(13) << "KiB/tile"
            << std::setw(10) << "of raw"
            << "\n"
            << std::fixed;
  nlohmann::json json = nlohmann::json::array();
  for (const ZstdResult& r : results) {
    std::cout << std::left << std::setw(28) << r.setting.name << std::right << std::setprecision(3)
              << std::setw(14) << r.compress_ms << std::setw(15) << r.decompress_ms
              << std::setprecision(1) << std::setw(13) << r.kib_per_tile << std::setprecision(3)
              << std::setw(10) << r.ratio << "\n";
    json.push_back({{"setting", r.setting.name},
                    {"level", r.setting.level},
                    {"literals_coded", r.setting.literals_coded},
                    {"hash_log", r.setting.hash_log},
                    {"compress_cpu_ms_per_tile", r.compress_ms},
                    {"decompress_cpu_ms_per_tile", r.decompress_ms},
                    {"kib_per_tile", r.kib_per_tile},
                    {"ratio", r.ratio}});
  }
  if (!json_path.empty()) {
    std::ofstream(json_path) << nlohmann::json{
        {"benchmark", "store_bench --zstd-tiles"},
        {"tiles", tiles.size()},
        {"libzstd", ZSTD_versionString()},
        {"settings", json}}.dump(2);
  }
  return 0;
}

int main(int argc, char** argv) {
  int frames = 375, publish_every = 12;
  double fps = 25.0;
  std::string json_path;
  fs::path zstd_tiles;
  fs::path dir = fs::temp_directory_path() / ("store_bench_" + std::to_string(::getpid()));
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string key = argv[i], value = argv[i + 1];
    if (key == "--frames")
      frames = std::stoi(value);
    else if (key == "--publish_every")
      publish_every = std::stoi(value);
    else if (key == "--fps")
      fps = std::stod(value);
    else if (key == "--json")
      json_path = value;
    else if (key == "--dir")
      dir = value;
    else if (key == "--zstd-tiles")
      zstd_tiles = value;
    else {
      std::cerr << "usage: store_bench [--frames N] [--publish_every N] [--fps F] [--json FILE]"
                   " [--dir DIR] [--zstd-tiles DIR]\n";
      return 2;
    }
  }
  if (!zstd_tiles.empty()) return RunZstdSettings(zstd_tiles, json_path);
  const cv::Mat ground = MakeGround(4096);
  const std::vector<std::pair<std::string, int>> configs = {
      {"ZSTD", 1}, {"ZSTD", 9}, {"DEFLATE", 1}, {"DEFLATE", 6}, {"NONE", 1}};
  std::vector<Result> results;
  for (const auto& [compression, level] : frames > 0 ? configs : decltype(configs){}) {
    results.push_back(
        RunFlight(compression, level, ground, frames, publish_every, fps, dir / compression));
  }
  std::vector<std::pair<int, double>> frames_cost;
  for (int existing : {1000, 15000, 90000}) {  // 90,000: an hour at 25 fps.
    frames_cost.emplace_back(existing, FramesPublishMs(existing, dir / "frames"));
  }
  const TileCost tile_cost =
      MeasureTileCost(ground, irmosaic::PixelType::kUInt16, 40, 5, dir / "tile_cost");
  const TileCost tile_cost8 =
      MeasureTileCost(ground, irmosaic::PixelType::kByte, 40, 5, dir / "tile_cost");
  const PaintCost paint_cost8 = MeasurePaintCost(irmosaic::PixelType::kByte, dir / "paint");
  const PaintCost paint_cost16 = MeasurePaintCost(irmosaic::PixelType::kUInt16, dir / "paint");
  std::vector<std::pair<int, double>> index_cost;
  for (int existing : {1000, 10000, 40000}) {
    index_cost.emplace_back(existing, IndexPublishMs(existing, dir / "index"));
  }
  std::vector<std::pair<int, RepaintIndexCost>> repaint_cost;
  for (int blocks : {100, 1000, 4000}) {
    repaint_cost.emplace_back(blocks, RepaintIndexPublish(blocks, dir / "repaint"));
  }
  fs::remove_all(dir);

  std::cout << "store_bench: " << frames << " frames of 640x512 UInt16 at " << fps
            << " fps, publish every " << publish_every << " frames, tile 512\n\n";
  std::cout << std::left << std::setw(11) << "compress" << std::right << std::setw(10) << "paint ms"
            << std::setw(9) << "p99" << std::setw(9) << "max" << std::setw(11) << "writer ms"
            << std::setw(12) << "publish p50" << std::setw(8) << "p99" << std::setw(13)
            << "frame->pub" << std::setw(8) << "p99" << std::setw(10) << "KB/frame" << std::setw(12)
            << "written KB"
            << "\n";
  nlohmann::json json = nlohmann::json::array();
  std::cout << std::fixed;
  for (const Result& r : results) {
    std::cout << std::left << std::setw(11) << r.compression << std::right << std::setprecision(2)
              << std::setw(10) << r.paint_mean_ms << std::setw(9) << r.paint_p99_ms << std::setw(9)
              << r.paint_max_ms << std::setw(11) << r.writer_ms_per_frame << std::setprecision(1)
              << std::setw(12) << r.publish_p50_ms << std::setw(8) << r.publish_p99_ms
              << std::setw(13) << r.frame_to_published_p50_ms << std::setw(8)
              << r.frame_to_published_p99_ms << std::setw(10) << r.store_kb_per_frame
              << std::setw(12) << r.written_kb_per_frame << "\n";
    json.push_back({{"compression", r.compression},
                    {"frames", r.frames},
                    {"paint_mean_ms", r.paint_mean_ms},
                    {"paint_p99_ms", r.paint_p99_ms},
                    {"paint_max_ms", r.paint_max_ms},
                    {"writer_ms_per_frame", r.writer_ms_per_frame},
                    {"output_ms_per_frame_amortised", r.paint_mean_ms + r.writer_ms_per_frame},
                    {"publish_p50_ms", r.publish_p50_ms},
                    {"publish_p99_ms", r.publish_p99_ms},
                    {"publish_max_ms", r.publish_max_ms},
                    {"frame_to_published_p50_ms", r.frame_to_published_p50_ms},
                    {"frame_to_published_p99_ms", r.frame_to_published_p99_ms},
                    {"frame_to_published_max_ms", r.frame_to_published_max_ms},
                    {"store_kb_per_frame", r.store_kb_per_frame},
                    {"written_kb_per_frame", r.written_kb_per_frame},
                    {"tiles_written", r.tiles_written},
                    {"publishes", r.publishes},
                    {"wall_s", r.wall_s}});
  }
  std::cout << "\npaint ms: calling thread per frame (Paint + RequestPublish); writer ms: writer "
               "thread work per frame, amortised;\nframe->pub: a frame's Paint to its generation "
               "published (ms); KB/frame: final store size / frames.\n";
  nlohmann::json frames_json = nlohmann::json::array();
  for (const auto& [existing, ms] : frames_cost) {
    std::cout << "publish of 25 frame records with " << existing
              << " already in frames.gpkg: " << std::setprecision(1) << ms << " ms (median)\n";
    frames_json.push_back({{"existing_records", existing}, {"publish_ms_median", ms}});
  }
  for (const auto& [name, cost] : {std::pair{"UInt16", tile_cost}, std::pair{"Byte", tile_cost8}}) {
    std::cout << "one 512 x 512 " << name << " tile (ZSTD 1), CPU ms on one thread: write "
              << std::setprecision(2) << cost.write_ms << " (" << cost.bytes / 1024
              << " KiB; through GDAL's encoding " << cost.write_gdal_ms << ", "
              << cost.gdal_bytes / 1024 << " KiB; one block of four changed "
              << cost.write_one_block_ms << "; an edge tile " << cost.write_edge_ms
              << "), read back " << cost.read_ms << " (through GDAL's decoding "
              << cost.read_gdal_ms << "), halve " << cost.halve_ms
              << " (an edge tile, half covered " << cost.halve_edge_ms
              << ") (minimum of 5 rounds of 40)\n";
  }
  for (const auto& [name, cost] :
       {std::pair{"Byte", paint_cost8}, std::pair{"UInt16", paint_cost16}}) {
    std::cout << "Paint of a 1000 x 960 " << name
              << " patch (an oblique footprint's box, feathered) over covered tiles, CPU ms on one "
                 "thread: AVX2 "
              << std::setprecision(3) << cost.avx2_ms << ", SSE2 " << cost.sse2_ms
              << " (minimum of 5 rounds of 30)\n";
  }
  nlohmann::json index_json = nlohmann::json::array();
  for (const auto& [existing, ms] : index_cost) {
    std::cout << "writer CPU of a publish adding 1 tile to " << existing
              << " level-0 tiles: " << std::setprecision(2) << ms << " ms (median of 9)\n";
    index_json.push_back({{"existing_tiles", existing}, {"publish_writer_cpu_ms", ms}});
  }
  nlohmann::json repaint_json = nlohmann::json::array();
  for (const auto& [blocks, cost] : repaint_cost) {
    std::cout << "a publish repainting 1 tile of a store of " << blocks
              << " blocks (a tile each): writer CPU " << std::setprecision(2) << cost.writer_cpu_ms
              << " ms, index written " << std::setprecision(1) << cost.index_kib
              << " KiB (medians of 9)\n";
    repaint_json.push_back({{"blocks", blocks},
                            {"publish_writer_cpu_ms", cost.writer_cpu_ms},
                            {"index_kib_written", cost.index_kib}});
  }
  if (!json_path.empty()) {
    std::ofstream(json_path)
        << nlohmann::json{{"benchmark", "store_bench"},
                          {"index_publish", index_json},
                          {"repaint_publish", repaint_json},
                          {"paint_byte_avx2_cpu_ms", paint_cost8.avx2_ms},
                          {"paint_byte_sse2_cpu_ms", paint_cost8.sse2_ms},
                          {"paint_uint16_avx2_cpu_ms", paint_cost16.avx2_ms},
                          {"paint_uint16_sse2_cpu_ms", paint_cost16.sse2_ms},
                          {"tile_write_cpu_ms", tile_cost.write_ms},
                          {"tile_write_gdal_cpu_ms", tile_cost.write_gdal_ms},
                          {"byte_tile_write_gdal_cpu_ms", tile_cost8.write_gdal_ms},
                          {"tile_write_one_block_cpu_ms", tile_cost.write_one_block_ms},
                          {"byte_tile_write_one_block_cpu_ms", tile_cost8.write_one_block_ms},
                          {"edge_tile_write_cpu_ms", tile_cost.write_edge_ms},
                          {"byte_edge_tile_write_cpu_ms", tile_cost8.write_edge_ms},
                          {"tile_read_cpu_ms", tile_cost.read_ms},
                          {"tile_read_gdal_cpu_ms", tile_cost.read_gdal_ms},
                          {"byte_tile_write_cpu_ms", tile_cost8.write_ms},
                          {"byte_tile_read_cpu_ms", tile_cost8.read_ms},
                          {"byte_tile_read_gdal_cpu_ms", tile_cost8.read_gdal_ms},
                          {"tile_halve_cpu_ms", tile_cost.halve_ms},
                          {"edge_tile_halve_cpu_ms", tile_cost.halve_edge_ms},
                          {"byte_tile_halve_cpu_ms", tile_cost8.halve_ms},
                          {"byte_edge_tile_halve_cpu_ms", tile_cost8.halve_edge_ms},
                          {"tile_bytes", tile_cost.bytes},
                          {"frames", frames},
                          {"fps", fps},
                          {"publish_every", publish_every},
                          {"results", json},
                          {"frames_gpkg", frames_json}}
               .dump(1)
        << "\n";
  }
  return 0;
}
