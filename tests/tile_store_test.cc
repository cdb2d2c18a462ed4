// TileStore: what GDAL (a real client) reads from the live store, under concurrency and crashes.
#include "irmosaic/tile_store.h"

#include <gdal.h>
#include <gdal_priv.h>
#include <gtest/gtest.h>
#include <ogr_spatialref.h>
#include <ogrsf_frmts.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <GeographicLib/Geodesic.hpp>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iterator>
#include <mutex>
#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <set>
#include <stdexcept>
#include <thread>
#include <tuple>

#include "../src/simd_dispatch.h"
#include "../src/store_internal.h"
#include "frames_gpkg_lock.h"
#include "irmosaic/error.h"
#include "irmosaic/local_frame.h"
#include "manifest_tiles.h"

namespace irmosaic {
namespace {

namespace fs = std::filesystem;
constexpr double kLat0 = 47.2, kLon0 = 8.5, kGsd = 0.5;

// A file's whole content (empty if it cannot be read), to compare files byte for byte.
std::string FileBytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

fs::path FreshDir(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() /
                       ("irmosaic_store_test_" + std::to_string(::getpid()) + "_" + name);
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

StoreGeoreference Georef() {
  const LocalFrame frame(kLat0, kLon0);
  return {kLat0, kLon0, kGsd, frame.CrsWkt()};
}

TileStoreOptions Options(const fs::path& path, int tile_size = 256) {
  TileStoreOptions options;
  options.path = path.string();
  options.tile_size = tile_size;
  return options;
}

void PaintSquare(TileStore* store, cv::Point top_left, int size, double value, float weight = 1.0f,
                 PaintKind kind = PaintKind::kNew) {
  cv::Mat image(size, size, CvDepthOf(store->pixel_type()), cv::Scalar(value));
  cv::Mat w(size, size, CV_32F, cv::Scalar(weight));
  store->Paint(image, w, top_left, kind);
}

// Counts GDAL failures of this thread while alive.
struct GdalErrorCount {
  GdalErrorCount() { CPLPushErrorHandlerEx(&Handler, this); }
  ~GdalErrorCount() { CPLPopErrorHandler(); }
  static void CPL_STDCALL Handler(CPLErr level, CPLErrorNum, const char* message) {
    auto* self = static_cast<GdalErrorCount*>(CPLGetErrorHandlerUserData());
    if (level >= CE_Failure) {
      ++self->count;
      self->last = message ? message : "";
    }
  }
  int count = 0;
  std::string last;
};

struct Raster {
  cv::Mat data, alpha;
  double gt[6];
  int overviews = 0;
  int64_t generation = -1;
};

// The sources a VRT file lists (<SimpleSource> elements).
size_t VrtSources(const fs::path& path) {
  std::ifstream in(path);
  const std::string xml((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  size_t n = 0;
  for (size_t at = xml.find("<SimpleSource>"); at != std::string::npos;
       at = xml.find("<SimpleSource>", at + 1)) {
    ++n;
  }
  return n;
}

// Reads mosaic.vrt (or any 2-band raster) whole through GDAL, optionally at an overview.
Raster ReadThroughGdal(const fs::path& path, int overview = 0) {
  Raster r;
  GDALAllRegister();  // The store may have been written by another process only.
  GDALDatasetH ds = GDALOpen(path.c_str(), GA_ReadOnly);
  if (ds == nullptr) return r;
  GDALGetGeoTransform(ds, r.gt);
  const char* gen = GDALGetMetadataItem(ds, "IRMOSAIC_GENERATION", nullptr);
  if (gen) r.generation = std::atoll(gen);
  GDALRasterBandH band1 = GDALGetRasterBand(ds, 1), band2 = GDALGetRasterBand(ds, 2);
  r.overviews = GDALGetOverviewCount(band1);
  if (overview > 0) {
    if (overview > r.overviews) {
      GDALClose(ds);
      return r;
    }
    band1 = GDALGetOverview(band1, overview - 1);
    band2 = GDALGetOverview(band2, overview - 1);
  }
  const int w = GDALGetRasterBandXSize(band1), h = GDALGetRasterBandYSize(band1);
  r.data.create(h, w, CV_32F);
  r.alpha.create(h, w, CV_32F);
  if (GDALRasterIO(band1, GF_Read, 0, 0, w, h, r.data.ptr(), w, h, GDT_Float32, 0, 0) != CE_None ||
      GDALRasterIO(band2, GF_Read, 0, 0, w, h, r.alpha.ptr(), w, h, GDT_Float32, 0, 0) != CE_None) {
    r.data.release();
  }
  GDALClose(ds);
  return r;
}

// Metres between plane points a and b measured on the ellipsoid through PROJ (independent of the
// store's own geotransform arithmetic).
double GroundDistance(const PlaneToGeographic& to_geo, const Eigen::Vector2d& a,
                      const Eigen::Vector2d& b) {
  const Eigen::Vector2d la = to_geo.LatLonFromPlane(a), lb = to_geo.LatLonFromPlane(b);
  double s12 = 0;
  GeographicLib::Geodesic::WGS84().Inverse(la.x(), la.y(), lb.x(), lb.y(), s12);
  return s12;
}

TEST(TileStoreTest, GdalReadsPaintedMarkersAtTheirGroundPositionWithExactValues) {
  const fs::path dir = FreshDir("markers") / "flight.irmosaic";
  auto store = TileStore::Open(Options(dir), Georef());
  // Markers straddling tile borders and negative tile indices, with distinct values.
  struct Marker {
    cv::Point top_left;
    int value;
  };
  const std::vector<Marker> markers = {
      {{-300, -40}, 1111}, {{250, 250}, 2222}, {{600, -500}, 3333}, {{-20, 700}, 4444}};
  for (const Marker& m : markers) PaintSquare(store.get(), m.top_left, 16, m.value);
  store->WaitPublished(store->RequestPublish());
  EXPECT_EQ(store->published_generation(), 1);

  GdalErrorCount errors;
  const Raster vrt = ReadThroughGdal(dir / "mosaic.vrt");
  ASSERT_FALSE(vrt.data.empty());
  EXPECT_EQ(vrt.generation, 1);
  // CRS: the mosaic plane's, as GDAL reports it.
  GDALDatasetH ds = GDALOpen((dir / "mosaic.vrt").c_str(), GA_ReadOnly);
  OGRSpatialReference expected, actual;
  expected.importFromWkt(Georef().crs_wkt.c_str());
  actual.importFromWkt(GDALGetProjectionRef(ds));
  EXPECT_TRUE(actual.IsSame(&expected));
  GDALClose(ds);

  const PlaneToGeographic to_geo{LocalFrame(kLat0, kLon0)};
  const MosaicGrid grid{kGsd};
  for (const Marker& m : markers) {
    // Where GDAL says the marker is: centroid of pixels holding its value, through the
    // geotransform.
    cv::Mat hit = vrt.data == m.value;
    const cv::Moments moments = cv::moments(hit, true);
    ASSERT_EQ(moments.m00, 16 * 16) << "value " << m.value << " must round-trip exactly";
    const double px = moments.m10 / moments.m00 + 0.5, py = moments.m01 / moments.m00 + 0.5;
    const Eigen::Vector2d gdal_xy(vrt.gt[0] + px * vrt.gt[1], vrt.gt[3] + py * vrt.gt[5]);
    // Where it was painted: the centre of the 16x16 block of mosaic pixels.
    const Eigen::Vector2d truth = grid.PlaneFromPixel({m.top_left.x + 7.5, m.top_left.y + 7.5});
    EXPECT_LT(GroundDistance(to_geo, gdal_xy, truth), kGsd) << "marker " << m.value;
    // Coverage: alpha is the UInt16 maximum on the marker.
    EXPECT_EQ(cv::countNonZero((vrt.alpha == 65535) & hit), 16 * 16);
  }
  // Unpainted pixels are transparent.
  EXPECT_EQ(cv::countNonZero(vrt.alpha), static_cast<int>(markers.size()) * 16 * 16);
  // Overviews: the extent spans 5 tiles, so levels exist, and level 1 shows each marker halved.
  ASSERT_GE(vrt.overviews, 2);
  const Raster level1 = ReadThroughGdal(dir / "mosaic.vrt", 1);
  ASSERT_FALSE(level1.data.empty());
  EXPECT_EQ(level1.data.cols, vrt.data.cols / 2);
  for (const Marker& m : markers) {
    EXPECT_EQ(cv::countNonZero(level1.data == m.value), 8 * 8) << "marker " << m.value;
  }
  EXPECT_EQ(errors.count, 0) << errors.last;

  // The manifest lists what GDAL read.
  std::ifstream in(dir / "manifest.json");
  const nlohmann::json manifest = nlohmann::json::parse(in);
  EXPECT_EQ(manifest["format"], "irmosaic-store");
  EXPECT_EQ(manifest["generation"], 1);
  EXPECT_EQ(manifest["data_type"], "UInt16");
  EXPECT_EQ(manifest_json::LevelTiles(manifest["levels"][0]).size(), 7u);  // 2222 straddles four.
  store->Close();
}

TEST(TileStoreTest, AReaderOpenedEarlyStillReadsOverviewsAfterTheMosaicGrew) {
  const fs::path dir = FreshDir("late_overviews") / "s.irmosaic";
  auto store = TileStore::Open(Options(dir), Georef());
  PaintSquare(store.get(), {0, 0}, 600, 3000);  // 3x3 tiles: overview levels exist.
  store->WaitPublished(store->RequestPublish());
  GDALAllRegister();
  GDALDatasetH early = GDALOpen((dir / "mosaic.vrt").c_str(), GA_ReadOnly);
  ASSERT_NE(early, nullptr);
  const int width = GDALGetRasterXSize(early);
  // The mosaic grows westward and southward over several publishes; then the early reader
  // zooms out (GDAL opens the overview VRTs only now).
  for (int i = 1; i <= 6; ++i) {
    PaintSquare(store.get(), {-300 * i, 300 * i}, 300, 3000 + i);
    store->WaitPublished(store->RequestPublish());
  }
  GdalErrorCount errors;
  GDALRasterBandH overview = GDALGetOverview(GDALGetRasterBand(early, 1), 0);
  ASSERT_NE(overview, nullptr) << errors.last;
  EXPECT_EQ(GDALGetRasterBandXSize(overview), width / 2);
  cv::Mat level1(GDALGetRasterBandYSize(overview), GDALGetRasterBandXSize(overview), CV_16U);
  EXPECT_EQ(GDALRasterIO(overview, GF_Read, 0, 0, level1.cols, level1.rows, level1.ptr(),
                         level1.cols, level1.rows, GDT_UInt16, 0, 0),
            CE_None);
  // The early extent's content, at its place: the 600x600 square halved.
  EXPECT_EQ(cv::countNonZero(level1 == 3000), 300 * 300);
  EXPECT_EQ(errors.count, 0) << errors.last;
  GDALClose(early);
  store->Close();
}

// mosaic.vrt's extent (and so its overview VRTs' names) grows in steps of a power of two no
// larger than a sixteenth of the span, per axis: it holds the painted tiles, pads each side by at
// most a sixteenth of the span (none below 32 tiles), and a mosaic growing tile by tile to 4096
// tiles changes it a few hundred times, not 4096.
TEST(TileStoreTest, VrtExtentGrowsInStepsOfASixteenthOfTheSpan) {
  int changes = 0;
  store::TileBounds last{0, 0, 0, 0};
  for (int64_t n = 1; n <= 4096; ++n) {
    // Rows fixed at 5 tiles; columns grow both ways, a third of the growth westward.
    const store::TileBounds painted{-3, 2, -(n / 3), n - n / 3};
    const store::TileBounds b = store::VrtBounds(painted);
    EXPECT_EQ(b.row0, painted.row0);  // A span under 32 tiles: exact.
    EXPECT_EQ(b.row1, painted.row1);
    const int64_t span = painted.col1 - painted.col0;
    ASSERT_LE(b.col0, painted.col0) << n;
    ASSERT_GE(b.col1, painted.col1) << n;
    ASSERT_LE(painted.col0 - b.col0, span / 16) << n;
    ASSERT_LE(b.col1 - painted.col1, span / 16) << n;
    if (span < 32) {
      ASSERT_EQ(b.col0, painted.col0) << n;
      ASSERT_EQ(b.col1, painted.col1) << n;
    }
    if (b.row0 != last.row0 || b.row1 != last.row1 || b.col0 != last.col0 || b.col1 != last.col1) {
      ++changes;
    }
    last = b;
  }
  // Exact bounds change at every step; ~16 per doubling and side here (2 sides, 7 doublings
  // past 32 tiles and one more as margin, plus the first 31 steps; 151 measured).
  EXPECT_LT(changes, 31 + 2 * 16 * 8);
}

// The level VRTs (level 0's and the overviews') are rewritten only when their extent or their
// level's blocks change; a publish that adds tiles to existing blocks rewrites mosaic.vrt (its
// generation: a few KiB, two sources) and the blocks' own VRTs only. GDAL reads the new tiles
// through the unchanged level VRTs, and the padded extent keeps every tile at its ground
// position.
TEST(TileStoreTest, OverviewVrtsAreRewrittenOnlyWhenTheirBlocksOrExtentChange) {
  const fs::path dir = FreshDir("overview_rewrites") / "s.irmosaic";
  constexpr int kTile = 64;
  TileStoreOptions options = Options(dir, kTile);
  options.pixel_type = PixelType::kByte;
  options.overview_interval_s = 0.0;  // Overviews within every publish.
  auto store = TileStore::Open(options, Georef());
  const auto at = [](int row, int col) { return cv::Point(col * kTile + 8, row * kTile + 8); };
  // Tiles (0, 0) and (40, 40): 41 x 41 tiles, padded to 42 x 42 (steps of 2 tiles).
  PaintSquare(store.get(), at(0, 0), 16, 10);
  PaintSquare(store.get(), at(40, 40), 16, 20);
  store->WaitPublished(store->RequestPublish());
  const auto names = [&] {
    return nlohmann::json::parse(std::ifstream(dir / "manifest.json"))["overview_vrts"]
        .get<std::vector<std::string>>();
  };
  const auto inode = [&](const std::string& relative) {
    struct stat st {};
    return ::stat((dir / relative).c_str(), &st) == 0 ? st.st_ino : ino_t{0};
  };
  const auto level0 = [&] {
    return nlohmann::json::parse(std::ifstream(dir / "manifest.json"))["level0_vrt"]
        .get<std::string>();
  };
  const auto sources = [&](const std::string& relative) { return VrtSources(dir / relative); };
  const std::vector<std::string> first = names();
  ASSERT_GE(first.size(), 2u);
  std::vector<ino_t> inodes;
  for (const std::string& vrt : first) inodes.push_back(inode(vrt));
  const ino_t mosaic_inode = inode("mosaic.vrt");
  const std::string first_level0 = level0();
  ASSERT_TRUE(fs::exists(dir / first_level0)) << first_level0;
  const ino_t level0_inode = inode(first_level0);
  EXPECT_EQ(sources("mosaic.vrt"), 2u);  // Level 0's VRT, in two bands.
  EXPECT_EQ(sources(first_level0), 4u);  // Blocks (0, 0) and (2, 2), two bands.
  EXPECT_LT(fs::file_size(dir / "mosaic.vrt"), 8192u);

  GdalErrorCount errors;
  Raster r = ReadThroughGdal(dir / "mosaic.vrt");
  ASSERT_FALSE(r.data.empty()) << errors.last;
  EXPECT_EQ(r.data.cols, 42 * kTile);
  EXPECT_EQ(r.data.rows, 42 * kTile);
  // Pixel (col, row) of level 0 is centred at plane (col, -row) * gsd: the VRT's first pixel.
  EXPECT_NEAR(r.gt[0], -0.5 * kGsd, 1e-9);
  EXPECT_NEAR(r.gt[3], 0.5 * kGsd, 1e-9);
  EXPECT_EQ(r.data.at<float>(40 * kTile + 8, 40 * kTile + 8), 20.0f);
  EXPECT_EQ(cv::countNonZero(r.alpha), 2 * 16 * 16);

  // Tile (40, 39): its blocks exist at every level (level 0: block (2, 2); level 1: (1, 1); ...).
  PaintSquare(store.get(), at(40, 39), 16, 30);
  store->WaitPublished(store->RequestPublish());
  EXPECT_EQ(names(), first);
  for (size_t l = 0; l < first.size(); ++l) {
    EXPECT_EQ(inode(first[l]), inodes[l]) << "level " << l + 1 << " was rewritten";
  }
  EXPECT_NE(inode("mosaic.vrt"), mosaic_inode);
  EXPECT_EQ(level0(), first_level0);
  EXPECT_EQ(inode(first_level0), level0_inode) << "level 0's VRT was rewritten";
  r = ReadThroughGdal(dir / "mosaic.vrt", 1);
  ASSERT_FALSE(r.data.empty()) << errors.last;
  EXPECT_EQ(r.generation, 2);
  EXPECT_EQ(cv::countNonZero(r.data == 30), 8 * 8);  // Through the unchanged level-1 VRT.

  // Tile (0, 40): a new block at level 0 ((0, 2)) and level 1 ((0, 1)), same extent: the level-1
  // VRT is rewritten under its name.
  PaintSquare(store.get(), at(0, 40), 16, 40);
  store->WaitPublished(store->RequestPublish());
  EXPECT_EQ(names(), first);
  EXPECT_NE(inode(first[0]), inodes[0]);
  EXPECT_EQ(level0(), first_level0);
  EXPECT_NE(inode(first_level0), level0_inode);
  EXPECT_EQ(sources(first_level0), 6u);
  r = ReadThroughGdal(dir / "mosaic.vrt", 1);
  ASSERT_FALSE(r.data.empty()) << errors.last;
  EXPECT_EQ(cv::countNonZero(r.data == 40), 8 * 8);
  EXPECT_EQ(cv::countNonZero(r.data == 10), 8 * 8);

  // Tile (0, 41): the painted extent grows (42 columns) within the padded one: nothing renamed.
  // Tile (0, 42) then widens it to 44 columns: new names, the old files kept for older readers.
  PaintSquare(store.get(), at(0, 41), 16, 50);
  store->WaitPublished(store->RequestPublish());
  EXPECT_EQ(names(), first);
  PaintSquare(store.get(), at(0, 42), 16, 60);
  store->WaitPublished(store->RequestPublish());
  const std::vector<std::string> wider = names();
  ASSERT_EQ(wider.size(), first.size());
  EXPECT_NE(wider[0], first[0]);
  EXPECT_NE(level0(), first_level0);
  for (const std::string& vrt : first) EXPECT_TRUE(fs::exists(dir / vrt)) << vrt;
  EXPECT_TRUE(fs::exists(dir / first_level0)) << first_level0;
  r = ReadThroughGdal(dir / "mosaic.vrt");
  ASSERT_FALSE(r.data.empty()) << errors.last;
  EXPECT_EQ(r.data.cols, 44 * kTile);
  for (const int value : {10, 20, 30, 40, 50, 60}) {
    EXPECT_EQ(cv::countNonZero(r.data == value), 16 * 16) << value;
  }
  EXPECT_EQ(r.data.at<float>(8, 42 * kTile + 8), 60.0f);
  EXPECT_EQ(errors.count, 0) << errors.last;
  store->Close();
}

// The index a publish writes grows with what changed, not with the store (docs/store.md,
// "mosaic.vrt"): the level VRTs name blocks of 16 x 16 tiles, each block its own VRT, and only
// blocks that gained tiles are rewritten. A flat VRT (one source per tile) would rewrite ~1 KB
// per tile and band on every publish: ~100 MB for the ~10^5 tiles of an hour's flight.
// The index's tile sets are blocks with bitmaps (store::LevelTiles): against a std::set of the
// same random tiles on both sides of 0 (block rows and columns below 0 are floor-divided), with
// tiles taken out again, whole blocks emptied, and a block read back from its bitmap.
TEST(TileStoreTest, LevelTilesAgreeWithASetOfTheSameTiles) {
  std::mt19937 rng(7);
  std::uniform_int_distribution<int64_t> coord(-40, 40);
  store::LevelTiles level;
  std::set<store::TileIndex> truth;
  for (int k = 0; k < 3000; ++k) {
    const store::TileIndex tile{coord(rng), coord(rng)};
    const bool erase = k % 3 == 2;
    const bool changed = erase ? level.erase(tile) : level.insert(tile);
    const bool expected = erase ? truth.erase(tile) == 1 : truth.insert(tile).second;
    ASSERT_EQ(changed, expected) << k;
  }
  // Empty a whole block: it leaves the block list.
  for (int64_t r = 0; r < 16; ++r) {
    for (int64_t c = -16; c < 0; ++c) {
      level.erase({r, c});
      truth.erase({r, c});
    }
  }
  EXPECT_EQ(level.blocks().count({0, -1}), 0u);
  ASSERT_EQ(level.size(), truth.size());
  const std::vector<store::TileIndex> listed = level.tiles();
  EXPECT_EQ(std::set<store::TileIndex>(listed.begin(), listed.end()), truth);
  EXPECT_EQ(listed.size(), truth.size());
  size_t in_blocks = 0;
  for (const auto& [block, rows] : level.blocks()) {
    EXPECT_GT(store::TilesIn(rows), 0);
    in_blocks += static_cast<size_t>(store::TilesIn(rows));
  }
  EXPECT_EQ(in_blocks, truth.size());
  for (int64_t r = -45; r <= 45; r += 5) {
    for (int64_t c = -45; c <= 45; ++c) {
      ASSERT_EQ(level.contains({r, c}), truth.count({r, c}) == 1) << r << "," << c;
    }
  }
  store::TileBounds expected{INT64_MAX, INT64_MIN, INT64_MAX, INT64_MIN};
  for (const auto& [row, col] : truth) {
    expected.row0 = std::min(expected.row0, row);
    expected.row1 = std::max(expected.row1, row + 1);
    expected.col0 = std::min(expected.col0, col);
    expected.col1 = std::max(expected.col1, col + 1);
  }
  const store::TileBounds b = level.bounds();
  EXPECT_EQ(std::tie(b.row0, b.row1, b.col0, b.col1),
            std::tie(expected.row0, expected.row1, expected.col0, expected.col1));
  // A single tile far from the others: bounds of one tile; a block rebuilt from its bitmap.
  store::LevelTiles one;
  one.insert({-17, 33});
  const store::TileBounds b1 = one.bounds();
  EXPECT_EQ(std::tie(b1.row0, b1.row1, b1.col0, b1.col1),
            std::make_tuple(int64_t{-17}, int64_t{-16}, int64_t{33}, int64_t{34}));
  store::LevelTiles copy;
  for (const auto& [block, rows] : level.blocks()) copy.InsertBlock(block, rows);
  EXPECT_TRUE(copy == level);
  EXPECT_EQ(copy.size(), level.size());
  EXPECT_TRUE(store::LevelTiles().empty());
}

TEST(TileStoreTest, IndexWrittenPerPublishIsBoundedByTheChangeNotTheStore) {
  const fs::path dir = FreshDir("index_cost") / "s.irmosaic";
  constexpr int kTile = 64;
  auto store = TileStore::Open(Options(dir, kTile), Georef());
  // 48 x 47 = 2256 tiles in 9 blocks, painted in strips with publishes between (as a flight).
  const cv::Size strip(47 * kTile, 8 * kTile);
  for (int row = 0; row < 48; row += 8) {
    store->Paint(cv::Mat(strip, CV_16U, cv::Scalar(1000 + row)),
                 cv::Mat(strip, CV_32F, cv::Scalar(1.0f)), {0, row * kTile});
    store->WaitPublished(store->RequestPublish());
  }
  const int64_t before = store->stats().index_bytes_total;
  // One new tile in an existing block (column 47 is in block 2), one in a new block far away.
  PaintSquare(store.get(), {47 * kTile + 8, 8}, 16, 7777);
  PaintSquare(store.get(), {-40 * kTile + 8, 8}, 16, 8888);
  store->WaitPublished(store->RequestPublish());
  const int64_t published = store->stats().index_bytes_total - before;
  std::ifstream in(dir / "manifest.json");
  const std::string manifest((std::istreambuf_iterator<char>(in)),
                             std::istreambuf_iterator<char>());
  const size_t tiles_all_levels =
      manifest_json::TileCountAllLevels(nlohmann::json::parse(manifest));
  // What one source costs in a VRT (a full block VRT lists 256 tiles in two bands).
  const int64_t block_bytes =
      static_cast<int64_t>(fs::file_size(dir / "tiles/0" / "block_r0_c0.vrt"));
  const int64_t source_bytes = block_bytes / (2 * 256);
  // Beyond the manifest: the two level-0 blocks that gained a tile, their parents' blocks at
  // the overview levels (at most two per level, each smaller than a full level-0 block), and
  // level VRTs of a source per block.
  const int64_t changed = static_cast<int64_t>(manifest.size()) + 2 * 2 * block_bytes;
  EXPECT_LT(published, changed);
  // A flat VRT would have listed every tile of every level in two bands.
  EXPECT_LT(published, static_cast<int64_t>(tiles_all_levels) * 2 * source_bytes / 3);
  // Level 0's VRT lists the blocks; mosaic.vrt lists it.
  const std::string level0 = nlohmann::json::parse(manifest)["level0_vrt"].get<std::string>();
  EXPECT_EQ(VrtSources(dir / level0), 2u * 10u);  // 9 + 1 blocks, two bands.
  EXPECT_EQ(VrtSources(dir / "mosaic.vrt"), 2u);

  // GDAL reads both new tiles through the nested VRTs, with every earlier strip intact.
  GdalErrorCount errors;
  const Raster r = ReadThroughGdal(dir / "mosaic.vrt");
  ASSERT_FALSE(r.data.empty()) << errors.last;
  EXPECT_EQ(cv::countNonZero(r.data == 7777), 16 * 16);
  EXPECT_EQ(cv::countNonZero(r.data == 8888), 16 * 16);
  for (int row = 0; row < 48; row += 8) {
    EXPECT_EQ(cv::countNonZero(r.data == 1000 + row), strip.area()) << row;
  }
  // Overviews follow at Close at the latest (overview_interval_s); level 2 through its blocks.
  store->Close();
  const Raster level2 = ReadThroughGdal(dir / "mosaic.vrt", 2);
  ASSERT_FALSE(level2.data.empty()) << errors.last;
  EXPECT_EQ(cv::countNonZero(level2.data == 7777), 4 * 4);
  EXPECT_EQ(cv::countNonZero(level2.data == 8888), 4 * 4);
  EXPECT_EQ(errors.count, 0) << errors.last;
}

TEST(TileStoreTest, BlendFollowsTheContractAndReadsBack) {
  const fs::path dir = FreshDir("blend") / "s.irmosaic";
  TileStoreOptions options = Options(dir);
  options.pixel_type = PixelType::kFloat32;
  auto store = TileStore::Open(options, Georef());
  PaintSquare(store.get(), {-10, -10}, 20, 100.0, 1.0f);
  PaintSquare(store.get(), {0, 0}, 20, 200.0, 0.25f);  // Half over covered, half over empty.
  cv::Mat image, coverage;
  store->ReadWindow({-10, -10, 30, 30}, &image, &coverage);
  EXPECT_FLOAT_EQ(image.at<float>(5, 5), 100.0f);                             // Only the first.
  EXPECT_FLOAT_EQ(image.at<float>(15, 15), 0.25f * 200.0f + 0.75f * 100.0f);  // Blended.
  EXPECT_FLOAT_EQ(image.at<float>(25, 25), 200.0f);  // Uncovered takes the patch.
  EXPECT_EQ(coverage.at<uchar>(25, 5), 0);
  EXPECT_EQ(cv::countNonZero(coverage), 20 * 20 + 20 * 20 - 10 * 10);
  // Zero weight paints nothing.
  PaintSquare(store.get(), {100, 100}, 8, 7.0, 0.0f);
  store->ReadWindow({100, 100, 8, 8}, &image, &coverage);
  EXPECT_EQ(cv::countNonZero(coverage), 0);
  // A patch of the wrong type is refused with a reason.
  EXPECT_THROW(store->Paint(cv::Mat(4, 4, CV_8U), cv::Mat(4, 4, CV_32F), {0, 0}), InputError);
  store->Close();
  // Float32 round-trips through GDAL exactly.
  const Raster vrt = ReadThroughGdal(dir / "mosaic.vrt");
  EXPECT_EQ(cv::countNonZero(vrt.data == 0.25f * 200.0f + 0.75f * 100.0f), 10 * 10);
}

// The UInt16 blend runs 8 samples per SSE2 vector and the rest one by one: both must follow the
// contract to the last count, with weights of every kind (NaN, negative, 0, fractional, 1, > 1),
// values at both ends of the range, over covered and uncovered samples, across a tile border.
// The blend's rule, sample by sample, for the integer types (SIMD for 8 samples at a time, the
// scalar loop for the rest; the same float operations and rounding).
template <typename T>
void ExpectBlendMatchesTheContractExactly(PixelType type, const std::string& name) {
  SCOPED_TRACE(name);
  constexpr int kMax = std::numeric_limits<T>::max();
  const int depth = cv::DataType<T>::depth;
  const fs::path dir = FreshDir(name) / "s.irmosaic";
  TileStoreOptions options = Options(dir, 64);
  options.pixel_type = type;
  auto store = TileStore::Open(options, Georef());
  std::mt19937 random(7);
  const cv::Rect area(50, 30, 61, 45);  // Odd width: vector and scalar samples, 4 tiles.
  cv::Mat base(area.size(), depth), base_w(area.size(), CV_32F);
  cv::randu(base, 0, kMax + 1);
  for (int y = 0; y < area.height; ++y) {
    for (int x = 0; x < area.width; ++x) base_w.at<float>(y, x) = random() % 2 ? 1.0f : 0.0f;
  }
  base.at<T>(0, 0) = kMax;
  base_w.at<float>(0, 0) = 1.0f;
  store->Paint(base, base_w, area.tl());
  cv::Mat patch(area.size(), depth), w(area.size(), CV_32F);
  cv::randu(patch, 0, kMax + 1);
  const std::array<float, 8> kinds = {
      std::numeric_limits<float>::quiet_NaN(), -0.5f, 0.0f, 1e-6f, 0.5f, 1.0f, 1.5f, 0.0f};
  for (int y = 0; y < area.height; ++y) {
    for (int x = 0; x < area.width; ++x) {
      const uint32_t pick = random() % 9;
      w.at<float>(y, x) =
          pick < 8 ? kinds[pick] : std::uniform_real_distribution<float>(0.0f, 1.0f)(random);
    }
  }
  patch.at<T>(0, 0) = 0;
  w.at<float>(0, 0) = 0.999f;  // Near a half: 65535 * 0.001 = 65.5.., 255 * 0.001 = 0.255.
  store->Paint(patch, w, area.tl());
  cv::Mat image, coverage;
  store->ReadWindow(area, &image, &coverage);
  ASSERT_EQ(image.depth(), depth);
  int wrong = 0;
  for (int y = 0; y < area.height; ++y) {
    for (int x = 0; x < area.width; ++x) {
      const float wx = w.at<float>(y, x);
      const bool was = base_w.at<float>(y, x) > 0.0f;
      T expected = was ? base.at<T>(y, x) : 0;
      if (wx > 0.0f) {
        expected = !was || wx >= 1.0f
                       ? patch.at<T>(y, x)
                       : cv::saturate_cast<T>(wx * static_cast<float>(patch.at<T>(y, x)) +
                                              (1.0f - wx) * static_cast<float>(base.at<T>(y, x)));
      }
      const bool covered = was || wx > 0.0f;
      wrong += image.at<T>(y, x) != expected || (coverage.at<uchar>(y, x) != 0) != covered;
    }
  }
  EXPECT_EQ(wrong, 0) << "of " << area.area() << " samples";
}

TEST(TileStoreTest, IntegerBlendMatchesTheContractExactly) {
  // AVX2 where the CPU has it (8 samples per vector of 8 floats), then SSE2's two vectors of 4.
  for (const bool avx2 : {true, false}) {
    SCOPED_TRACE(avx2 ? "AVX2 allowed" : "SSE2");
    const bool before = simd::SetAvx2Allowed(avx2);
    ExpectBlendMatchesTheContractExactly<uint16_t>(PixelType::kUInt16,
                                                   avx2 ? "blend16" : "blend16_sse2");
    ExpectBlendMatchesTheContractExactly<uint8_t>(PixelType::kByte,
                                                  avx2 ? "blend8" : "blend8_sse2");
    simd::SetAvx2Allowed(before);
  }
}

// The caller's state goes into manifest.json as the text it was given (the Mosaicker's is its
// optimizer window, ~0.4 MB at each publish): not parsed and formatted again by the writer.
TEST(TileStoreTest, ApplicationStateIsWrittenVerbatimAndReadsBack) {
  const fs::path dir = FreshDir("application") / "s.irmosaic";
  // Spacing, key order and a number's trailing zero that formatting the JSON again would change.
  const std::string state = R"({"window": [1.250, -0.5e1],  "frozen": {"frames": 3}})";
  {
    auto store = TileStore::Open(Options(dir), Georef());
    EXPECT_THROW(store->SetApplicationState(R"({"window": [1.25,)"), InputError);
    PaintSquare(store.get(), {0, 0}, 32, 500);
    store->SetApplicationState(state);
    store->WaitPublished(store->RequestPublish());
    std::ifstream in(dir / "manifest.json");
    const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    EXPECT_NE(text.find("\"application\": " + state + "\n}"), std::string::npos) << text;
    const nlohmann::json manifest = nlohmann::json::parse(text);  // Still one JSON document.
    EXPECT_EQ(manifest["application"], nlohmann::json::parse(state));
    EXPECT_EQ(manifest["format"], "irmosaic-store");
    store->SetApplicationState("");
    PaintSquare(store.get(), {64, 0}, 32, 500);
    store->WaitPublished(store->RequestPublish());
    EXPECT_TRUE(
        nlohmann::json::parse(std::ifstream(dir / "manifest.json"))["application"].is_null());
    store->SetApplicationState(state);
    store->Close();
  }
  TileStoreOptions resume = Options(dir);
  resume.mode = TileStoreOptions::Mode::kResume;
  auto store = TileStore::Open(resume, Georef());
  EXPECT_EQ(nlohmann::json::parse(store->application_state()), nlohmann::json::parse(state));
  store->Close();
}

TEST(TileStoreTest, ExistingStoreNeedsResumeOrOverwriteAndResumeContinues) {
  const fs::path dir = FreshDir("resume") / "s.irmosaic";
  {
    auto store = TileStore::Open(Options(dir), Georef());
    PaintSquare(store.get(), {0, 0}, 32, 500);
    FrameRecord record;
    record.index = 7;
    record.time_s = 12.5;
    record.footprint_m = {Eigen::Vector2d(0, 0), {10, 0}, {10, -10}, {0, -10}};
    record.status = "registered";
    store->PutFrameRecord(record);
    store->SetApplicationState(R"({"last_frame": 7})");
    store->Close();
  }
  try {
    TileStore::Open(Options(dir), Georef());
    FAIL() << "kCreate on an existing store must throw";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find(dir.string()), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("--resume"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("--overwrite"), std::string::npos) << e.what();
  }
  TileStoreOptions resume = Options(dir);
  resume.mode = TileStoreOptions::Mode::kResume;
  {
    auto store = TileStore::Open(resume, Georef());
    EXPECT_EQ(store->published_generation(), 1);
    EXPECT_EQ(store->application_state(), R"({"last_frame":7})");
    ASSERT_EQ(store->FrameRecords().size(), 1u);
    EXPECT_EQ(store->FrameRecords()[0].index, 7);
    EXPECT_DOUBLE_EQ(store->FrameRecords()[0].footprint_m[2].y(), -10.0);
    PaintSquare(store.get(), {1000, 0}, 32, 600);
    store->Close();
    EXPECT_EQ(store->published_generation(), 2);
  }
  const Raster vrt = ReadThroughGdal(dir / "mosaic.vrt");
  EXPECT_EQ(cv::countNonZero(vrt.data == 500), 32 * 32);
  EXPECT_EQ(cv::countNonZero(vrt.data == 600), 32 * 32);
  // Resume with another GSD is refused.
  StoreGeoreference other = Georef();
  other.gsd_m = 0.25;
  EXPECT_THROW(TileStore::Open(resume, other), InputError);
  // Overwrite refuses a folder that is not a store, and replaces a store.
  const fs::path not_store = FreshDir("notstore");
  std::ofstream(not_store / "precious.txt") << "data";
  TileStoreOptions overwrite = Options(not_store);
  overwrite.mode = TileStoreOptions::Mode::kOverwrite;
  EXPECT_THROW(TileStore::Open(overwrite, Georef()), InputError);
  EXPECT_TRUE(fs::exists(not_store / "precious.txt"));
  overwrite.path = dir.string();
  TileStore::Open(overwrite, Georef())->Close();
  EXPECT_EQ(cv::countNonZero(ReadThroughGdal(dir / "mosaic.vrt").alpha), 0);
}

TEST(TileStoreTest, FramesGpkgHoldsFootprintsInTheMosaicCrs) {
  const fs::path dir = FreshDir("frames") / "s.irmosaic";
  auto store = TileStore::Open(Options(dir), Georef());
  for (int i = 0; i < 30; ++i) {
    FrameRecord r;
    r.index = i;
    r.time_s = 0.04 * i;
    r.footprint_m = {Eigen::Vector2d(i, 0), {i + 50.0, 0}, {i + 50.0, -40}, {i, -40}};
    r.pos_only = i % 3 == 0;
    r.inliers = 100 + i;
    r.residual_px = 0.3;
    r.status = r.pos_only ? "pos_only" : "registered";
    store->PutFrameRecord(r);
  }
  store->WaitPublished(store->RequestPublish());
  FrameRecord replaced;
  replaced.index = 4;
  replaced.time_s = 0.16;
  replaced.footprint_m = {Eigen::Vector2d(1, 1), {2, 1}, {2, 0}, {1, 0}};
  replaced.status = "refined";
  store->PutFrameRecord(replaced);
  store->Close();

  GDALDataset* ds = GDALDataset::Open((dir / "frames.gpkg").c_str(), GDAL_OF_VECTOR);
  ASSERT_NE(ds, nullptr);
  OGRLayer* layer = ds->GetLayerByName("frames");
  ASSERT_NE(layer, nullptr);
  EXPECT_EQ(layer->GetFeatureCount(), 30);
  OGRSpatialReference expected;
  expected.importFromWkt(Georef().crs_wkt.c_str());
  EXPECT_TRUE(layer->GetSpatialRef()->IsSame(&expected));
  layer->SetAttributeFilter("frame_index = 4");
  OGRFeature* f = layer->GetNextFeature();
  ASSERT_NE(f, nullptr);
  EXPECT_STREQ(f->GetFieldAsString("status"), "refined");
  OGREnvelope env;
  f->GetGeometryRef()->getEnvelope(&env);
  EXPECT_DOUBLE_EQ(env.MaxX, 2.0);
  OGRFeature::DestroyFeature(f);
  layer->SetAttributeFilter("pos_only = 1");
  EXPECT_EQ(layer->GetFeatureCount(), 10);
  GDALClose(ds);
  std::ifstream in(dir / "manifest.json");
  const nlohmann::json manifest = nlohmann::json::parse(in);
  EXPECT_EQ(manifest["frames"]["count"], 30);
  EXPECT_DOUBLE_EQ(manifest["frames"]["time_max_s"].get<double>(), 0.04 * 29);
}

// manifest.json's frames.time_min_s / time_max_s follow the records: kept up to date as records
// come (not recomputed over the whole flight at each publish), redone when a record is replaced
// with another time, and taken from frames.gpkg on a resume.
TEST(TileStoreTest, ManifestTimeRangeFollowsTheRecordsAcrossReplacementAndResume) {
  const fs::path dir = FreshDir("time_range") / "s.irmosaic";
  auto range = [&dir] {
    std::ifstream in(dir / "manifest.json");
    const nlohmann::json frames = nlohmann::json::parse(in)["frames"];
    return std::make_tuple(frames["count"].get<int64_t>(), frames["time_min_s"].get<double>(),
                           frames["time_max_s"].get<double>());
  };
  auto record = [](int64_t index, double time_s) {
    FrameRecord r;
    r.index = index;
    r.time_s = time_s;
    r.footprint_m = {Eigen::Vector2d(0, 0), {10, 0}, {10, -10}, {0, -10}};
    r.status = "registered";
    return r;
  };
  {
    TileStoreOptions options = Options(dir);
    options.overview_interval_s = 0.0;  // frames.gpkg with every publish.
    auto store = TileStore::Open(options, Georef());
    for (int i = 0; i < 5; ++i) store->PutFrameRecord(record(i, 10.0 + i));
    store->WaitPublished(store->RequestPublish());
    EXPECT_EQ(range(), std::make_tuple(int64_t{5}, 10.0, 14.0));
    store->PutFrameRecord(record(7, 9.5));  // Extends it downwards.
    store->WaitPublished(store->RequestPublish());
    EXPECT_EQ(range(), std::make_tuple(int64_t{6}, 9.5, 14.0));
    store->PutFrameRecord(record(7, 12.0));  // The earliest record moves: the range shrinks.
    store->PutFrameRecord(record(4, 11.0));  // So does the latest.
    store->WaitPublished(store->RequestPublish());
    EXPECT_EQ(range(), std::make_tuple(int64_t{6}, 10.0, 13.0));
    store->Close();
  }
  TileStoreOptions resume = Options(dir);
  resume.mode = TileStoreOptions::Mode::kResume;
  auto store = TileStore::Open(resume, Georef());
  store->PutFrameRecord(record(8, 20.0));
  store->WaitPublished(store->RequestPublish());
  EXPECT_EQ(range(), std::make_tuple(int64_t{7}, 10.0, 20.0));
  store->Close();
}

// Runs `write` on a new store at `dir` (overview_interval_s 3600: overviews and frames.gpkg
// follow the tiles at the first publish, then not) in a child process that kills itself with
// SIGKILL when `write` returns, before Close() (the store's destructor) could bring them up to
// date. True if the child died by that kill.
bool WriteThenKill(const fs::path& dir, const std::function<void(TileStore*)>& write) {
  const pid_t writer = fork();
  if (writer == 0) {
    try {
      TileStoreOptions options = Options(dir);
      options.overview_interval_s = 3600.0;
      auto store = TileStore::Open(options, Georef());
      write(store.get());
      kill(getpid(), SIGKILL);
    } catch (...) {
      _exit(1);
    }
    _exit(2);
  }
  int status = 0;
  waitpid(writer, &status, 0);
  return WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL;
}

// frames.gpkg follows the tiles every overview_interval_s (the Mosaicker's 2 s), so a process
// killed between two of its updates left frames.gpkg without the records of its last published
// frames, and a resume did not bring them back (a CLI run killed and resumed lost up to 18 of
// 64 records, and frames re-rendered before the kill kept their old footprints, ~30 px off).
// The manifest holds the records frames.gpkg does not have yet (frames.pending): a reader of
// the killed store and the resumed store both have every record of the published generation.
TEST(TileStoreTest, ThePublishedRecordsSurviveAKillBeforeFramesGpkgFollows) {
  GDALAllRegister();  // The reads below come before this process opens a store.
  const fs::path dir = FreshDir("pending") / "s.irmosaic";
  const auto record = [](int64_t index, const std::string& status) {
    FrameRecord r;
    r.index = index;
    r.time_s = 0.04 * static_cast<double>(index);
    const double x = 20.0 * static_cast<double>(index) + (status == "moved" ? 7.0 : 0.0);
    r.footprint_m = {Eigen::Vector2d(x, 0), {x + 50.0, 0}, {x + 50.0, -40}, {x, -40}};
    r.inliers = 30;
    r.residual_px = 0.2;
    r.status = status;
    return r;
  };
  // frames.gpkg follows at the first publish, then not.
  ASSERT_TRUE(WriteThenKill(dir, [&](TileStore* store) {
    for (int i = 0; i < 10; ++i) store->PutFrameRecord(record(i, "registered"));
    PaintSquare(store, {0, 0}, 64, 1000.0);  // Tiles, so that overviews follow.
    store->WaitPublished(store->RequestPublish());
    PaintSquare(store, {300, 0}, 64, 1000.0);
    for (int i = 10; i < 20; ++i) store->PutFrameRecord(record(i, "registered"));
    store->PutFrameRecord(record(3, "moved"));  // A re-render moved frame 3.
    store->WaitPublished(store->RequestPublish());
  }));
  const auto summary = [](const std::vector<FrameRecord>& records) {
    std::string text = std::to_string(records.size()) + " records";
    for (const FrameRecord& r : records) {
      if (r.index == 3)
        text += ", frame 3 " + r.status + " at x " + std::to_string(r.footprint_m[0].x());
    }
    return text;
  };
  // frames.gpkg alone lags: the test kills where it means to.
  EXPECT_EQ(summary(store::ReadFramesGpkg(dir / "frames.gpkg")),
            "10 records, frame 3 registered at x 60.000000");
  // A reader of the killed store, and the resumed store once closed, have them all.
  EXPECT_EQ(summary(TileStore::OpenReadOnly(dir.string())->FrameRecords()),
            "20 records, frame 3 moved at x 67.000000");
  TileStoreOptions resume = Options(dir);
  resume.mode = TileStoreOptions::Mode::kResume;
  resume.overview_interval_s = 3600.0;
  {
    auto store = TileStore::Open(resume, Georef());
    EXPECT_EQ(summary(store->FrameRecords()), "20 records, frame 3 moved at x 67.000000");
    store->Close();
  }
  EXPECT_EQ(summary(store::ReadFramesGpkg(dir / "frames.gpkg")),
            "20 records, frame 3 moved at x 67.000000");
  std::ifstream in(dir / "manifest.json");
  const nlohmann::json frames = nlohmann::json::parse(in)["frames"];
  EXPECT_EQ(frames["count"], 20);
  EXPECT_TRUE(frames["pending"].empty());  // Close() wrote frames.gpkg: nothing pending.
}

// Overviews follow level 0 every overview_interval_s (the Mosaicker's 2 s), so a process killed
// between two overview updates left level 1 and up showing older content than level 0, and a
// resume never brought them up to date (a CLI run killed and resumed: 2-10 of 28 level-1 tiles
// differing from their level-0 tiles halved, by ~1000 counts). The index lists the level-0
// tiles the overviews owe (manifest overviews_owed); a resume brings those into the overviews.
TEST(TileStoreTest, OverviewsCatchUpAfterAKillBetweenOverviewUpdates) {
  GDALAllRegister();
  const fs::path dir = FreshDir("owed_overviews") / "s.irmosaic";
  // 256-pixel tiles: 2 x 2 of them, one level-1 tile; overviews at the first publish, then not.
  ASSERT_TRUE(WriteThenKill(dir, [](TileStore* store) {
    PaintSquare(store, {0, 0}, 512, 1000.0);
    store->WaitPublished(store->RequestPublish());
    while (store->stats().overviews_pending) {  // The first update's slices.
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    PaintSquare(store, {0, 0}, 512, 2000.0);
    store->WaitPublished(store->RequestPublish());
  }));
  const auto value_at_centre = [&dir](int level) {
    GDALDatasetUniquePtr tile(GDALDataset::Open(
        (dir / "tiles" / std::to_string(level) / "0_0.tif").c_str(), GDAL_OF_RASTER));
    if (!tile) return -1.0;
    double value = 0.0;
    if (tile->GetRasterBand(1)->RasterIO(GF_Read, 128, 128, 1, 1, &value, 1, 1, GDT_Float64, 0,
                                         0) != CE_None) {
      return -1.0;
    }
    return value;
  };
  // The kill came where the test means: level 0 new, level 1 still the first paint.
  EXPECT_EQ(value_at_centre(0), 2000.0);
  EXPECT_EQ(value_at_centre(1), 1000.0);
  TileStoreOptions resume = Options(dir);
  resume.mode = TileStoreOptions::Mode::kResume;
  resume.overview_interval_s = 3600.0;
  TileStore::Open(resume, Georef())->Close();  // Paints nothing.
  EXPECT_EQ(value_at_centre(1), 2000.0);
  std::ifstream in(dir / "manifest.json");
  EXPECT_TRUE(nlohmann::json::parse(in)["overviews_owed"].empty());
}

// The first publish brings the overviews and frames.gpkg whatever overview_interval_s says
// (the tests above rely on it). The clock used to start from a default time point, the steady
// clock's epoch, which is the machine's boot: on a machine up for less than the interval the
// first update never came, and the two kill tests above failed on a freshly booted VM (one hung
// waiting for it). An interval longer than any uptime makes that deterministic.
TEST(TileStoreTest, TheFirstPublishUpdatesTheOverviewsHoweverRecentlyTheMachineBooted) {
  const fs::path dir = FreshDir("first_update") / "s.irmosaic";
  TileStoreOptions options = Options(dir);
  options.overview_interval_s = 1e9;  // 31 years.
  auto store = TileStore::Open(options, Georef());
  FrameRecord record;
  record.index = 0;
  record.footprint_m = {Eigen::Vector2d(0, 0), {50, 0}, {50, -40}, {0, -40}};
  record.status = "registered";
  store->PutFrameRecord(record);
  PaintSquare(store.get(), {0, 0}, 512, 1000.0);
  store->WaitPublished(store->RequestPublish());
  EXPECT_EQ(store->stats().overview_updates, 1);
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (store->stats().overviews_pending && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  EXPECT_FALSE(store->stats().overviews_pending);
  EXPECT_EQ(store::ReadFramesGpkg(dir / "frames.gpkg").size(), 1u);
  // A second publish is not due by the clock: no second update.
  PaintSquare(store.get(), {0, 0}, 512, 2000.0);
  store->WaitPublished(store->RequestPublish());
  EXPECT_EQ(store->stats().overview_updates, 1);
}

// The store flushes its file system every sync_interval_s on a thread of its own (published
// tiles on the disk within about that long; on ext4 without a journal it keeps file creation
// cheap), never with 0; Close does not wait out a long interval; a negative or infinite interval
// is refused with the option named.
TEST(TileStoreTest, TheFileSystemIsFlushedEverySyncInterval) {
  const fs::path dir = FreshDir("sync");
  TileStoreOptions options = Options(dir / "a.irmosaic");
  options.sync_interval_s = 0.02;
  auto store = TileStore::Open(options, Georef());
  PaintSquare(store.get(), {0, 0}, 64, 1000.0);
  store->WaitPublished(store->RequestPublish());
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (store->stats().syncs < 3 && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  EXPECT_GE(store->stats().syncs, 3);
  store->Close();

  options = Options(dir / "b.irmosaic");
  options.sync_interval_s = 0.0;
  store = TileStore::Open(options, Georef());
  PaintSquare(store.get(), {0, 0}, 64, 1000.0);
  store->WaitPublished(store->RequestPublish());
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_EQ(store->stats().syncs, 0);
  store->Close();

  // Long intervals (one past what the clock's nanoseconds hold) wait, and Close wakes the
  // flusher instead of waiting them out.
  for (const double long_interval : {1e6, 1e300}) {
    options = Options(dir / "c.irmosaic");
    options.mode = TileStoreOptions::Mode::kOverwrite;
    options.sync_interval_s = long_interval;
    store = TileStore::Open(options, Georef());
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    const auto close_start = std::chrono::steady_clock::now();
    store->Close();
    EXPECT_LT(std::chrono::steady_clock::now() - close_start, std::chrono::seconds(60));
    EXPECT_EQ(store->stats().syncs, 0) << long_interval;
  }

  for (const double bad :
       {-1.0, std::numeric_limits<double>::infinity(), std::numeric_limits<double>::quiet_NaN()}) {
    options = Options(dir / "d.irmosaic");
    options.sync_interval_s = bad;
    try {
      TileStore::Open(options, Georef());
      ADD_FAILURE() << bad << " accepted";
    } catch (const InputError& e) {
      EXPECT_NE(std::string(e.what()).find("sync_interval_s"), std::string::npos) << e.what();
    }
  }
  fs::remove_all(dir);
}

// Bytes this process has passed to write(2) and its kin so far, all threads (/proc/self/io).
int64_t BytesWrittenByThisProcess() {
  std::ifstream io("/proc/self/io");
  std::string key;
  int64_t value = 0;
  while (io >> key >> value) {
    if (key == "wchar:") return value;
  }
  return -1;
}

FrameRecord Footprint(int64_t index, const std::string& status) {
  FrameRecord r;
  r.index = index;
  r.time_s = 0.04 * static_cast<double>(index);
  const double x = static_cast<double>(index % 100) * 20.0, y = -static_cast<double>(index / 100);
  r.footprint_m = {Eigen::Vector2d(x, y), {x + 50.0, y}, {x + 50.0, y - 40.0}, {x, y - 40.0}};
  r.inliers = 40;
  r.residual_px = 0.25;
  r.status = status;
  return r;
}

// An hour of flight is ~90,000 footprints: each update of frames.gpkg must cost what changed, not
// a copy of the whole file (which grows with the flight).
TEST(TileStoreTest, FramesUpdateWritesTheChangeNotTheWholeFile) {
  const fs::path dir = FreshDir("frames_cost") / "s.irmosaic";
  auto store = TileStore::Open(Options(dir), Georef());  // overview_interval_s 0: every publish.
  int64_t next = 0;
  // Writes 10 new records and replaces 10 old ones; returns the bytes written by that publish.
  const auto update = [&] {
    const int64_t old = next - 1000;  // Ten records 1000 frames back, different every time.
    for (int k = 0; k < 10; ++k) store->PutFrameRecord(Footprint(old + k, "refined"));
    for (int k = 0; k < 10; ++k) store->PutFrameRecord(Footprint(next++, "registered"));
    const int64_t before = BytesWrittenByThisProcess();
    store->WaitPublished(store->RequestPublish());
    return BytesWrittenByThisProcess() - before;
  };
  const auto grow_to = [&](int64_t count) {
    while (next < count) {
      for (int k = 0; k < 2000 && next < count; ++k) {
        store->PutFrameRecord(Footprint(next++, "registered"));
      }
      store->WaitPublished(store->RequestPublish());
    }
  };
  grow_to(2000);
  const int64_t small_store = update();
  grow_to(16000);
  const int64_t large_store = update();
  const int64_t file_bytes = static_cast<int64_t>(fs::file_size(dir / "frames.gpkg"));
  std::cout << "bytes written by a 20-record publish: " << small_store << " at 2,000 records, "
            << large_store << " at 16,000 (frames.gpkg " << file_bytes << " bytes)\n";
  ASSERT_GT(small_store, 0);
  // 8x the records, the same change: the same cost within a factor 2, far below the file.
  EXPECT_LT(large_store, 2 * small_store);
  EXPECT_LT(large_store, file_bytes / 8);
  store->Close();

  // Every record is there, the replaced ones replaced; the closed file is one file again
  // (SQLite rollback journal: header bytes 18-19 are 1, WAL would be 2), no -wal or -shm left.
  GDALDataset* ds = GDALDataset::Open((dir / "frames.gpkg").c_str(), GDAL_OF_VECTOR);
  ASSERT_NE(ds, nullptr);
  OGRLayer* layer = ds->GetLayerByName("frames");
  ASSERT_NE(layer, nullptr);
  EXPECT_EQ(layer->GetFeatureCount(), next);
  layer->SetAttributeFilter("status = 'refined'");
  EXPECT_EQ(layer->GetFeatureCount(), 20);
  GDALClose(ds);
  std::ifstream gpkg(dir / "frames.gpkg", std::ios::binary);
  char header[20] = {};
  gpkg.read(header, sizeof(header));
  EXPECT_EQ(header[18], 1);
  EXPECT_EQ(header[19], 1);
  EXPECT_FALSE(fs::exists(dir / "frames.gpkg-wal"));
  EXPECT_FALSE(fs::exists(dir / "frames.gpkg-shm"));
}

TEST(TileStoreTest, MemoryStaysBoundedAndEvictedTilesReloadExactly) {
  const fs::path dir = FreshDir("memory") / "s.irmosaic";
  TileStoreOptions options = Options(dir, 64);
  options.max_cached_tiles = 8;
  options.pixel_type = PixelType::kByte;
  auto store = TileStore::Open(options, Georef());
  size_t most_cached = 0;
  // A strip of 60 tiles, painted twice (second pass blends into reloaded tiles).
  for (int pass = 0; pass < 2; ++pass) {
    for (int i = 0; i < 60; ++i) {
      PaintSquare(store.get(), {i * 64, 0}, 64, pass == 0 ? 100 : 200, pass == 0 ? 1.0f : 0.5f);
      if (i % 10 == 9) store->RequestPublish();
      most_cached = std::max(most_cached, store->stats().cached_tiles);
    }
    store->WaitPublished(store->RequestPublish());
  }
  EXPECT_LE(most_cached, 2 * options.max_cached_tiles);
  EXPECT_GT(store->stats().tile_reloads, 0);
  cv::Mat image, coverage;
  store->ReadWindow({0, 0, 60 * 64, 64}, &image, &coverage);
  EXPECT_EQ(cv::countNonZero(image == 150), 60 * 64 * 64);
  store->Close();
}

// The two figures the live path steers by: how far the writer is behind (the map fusion pauses
// its re-renders above a bound) and when a generation reached the disk (publish latency).
TEST(TileStoreTest, BacklogAndPublishTimesFollowTheWriter) {
  const fs::path dir = FreshDir("backlog") / "s.irmosaic";
  TileStoreOptions options = Options(dir, 256);
  options.max_cached_tiles = 1024;
  options.pixel_type = PixelType::kUInt16;
  auto store = TileStore::Open(options, Georef());
  EXPECT_EQ(store->BacklogSeconds(), 0.0);
  EXPECT_FALSE(store->PublishedAt(1).has_value());
  // 8 x 8 tiles to write: the writer needs far longer than the calls below take.
  for (int row = 0; row < 8; ++row) PaintSquare(store.get(), {0, row * 256}, 8 * 256, 1000.0);
  const auto requested = std::chrono::steady_clock::now();
  const int64_t generation = store->RequestPublish();
  double most = 0.0;
  int samples = 0;
  while (store->published_generation() < generation) {
    const double backlog = store->BacklogSeconds();
    const double since =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - requested).count();
    EXPECT_LE(backlog, since + 1e-3);  // Counted from the request, never before it.
    most = std::max(most, backlog);
    ++samples;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  const auto waited = std::chrono::steady_clock::now();
  EXPECT_GT(samples, 0);
  EXPECT_GT(most, 0.0) << "the writer was never seen behind in " << samples << " samples";
  EXPECT_EQ(store->BacklogSeconds(), 0.0);
  const auto at = store->PublishedAt(generation);
  ASSERT_TRUE(at.has_value());
  EXPECT_GE(*at, requested);
  EXPECT_LE(*at, waited);
  // An earlier generation folded into this publish has the same time; a later one has none.
  EXPECT_EQ(store->PublishedAt(generation - 1), at);
  EXPECT_FALSE(store->PublishedAt(generation + 1).has_value());
  store->Close();
}

// Overview tiles: HalveTile's one-pass integer path gives exactly the coverage-weighted 2 x 2 mean
// of the float formula (HalveTile's Float32 path: weights, INTER_AREA sums, divide; then round to
// nearest even), over random values and coverage, the type's extremes and exact halves.
TEST(TileStoreTest, HalvedTilesEqualTheFloatFormula) {
  // The float formula is HalveTile's own path for Float32 tiles; its means rounded to the type.
  const auto reference = [](const store::TileImage& tile) {
    store::TileImage as_float{cv::Mat(), tile.alpha};
    tile.data.convertTo(as_float.data, CV_32F);
    store::TileImage half = store::HalveTile(as_float);
    half.data.convertTo(half.data, tile.data.depth());
    return half;
  };
  std::mt19937 random(7);
  for (const int depth : {CV_16U, CV_8U}) {
    const double top = depth == CV_16U ? 65535 : 255;
    store::TileImage tile{cv::Mat(64, 64, depth), cv::Mat(64, 64, CV_8U)};
    for (int trial = 0; trial < 20; ++trial) {
      cv::randu(tile.data, 0, top + 1);
      if (trial % 4 == 1) tile.data.setTo(top);        // Saturation.
      if (trial % 4 == 2) cv::randu(tile.data, 0, 4);  // Means of x.5 (to even) and x/3.
      // Every 5th trial all covered but a few samples: the vector blocks of a tile's inside
      // (8 UInt16 or 16 Byte outputs whose samples are all covered) beside blocks with a gap.
      // Every 5th trial from the 4th: a covered corner, the rest empty (as a tile at the edge
      // of the mosaic): vector blocks with no sample covered, and mixed ones along the edge.
      std::bernoulli_distribution cover(trial % 5 == 4 ? 0.998 : trial % 2 ? 0.5 : 0.9);
      for (int y = 0; y < 64; ++y) {
        for (int x = 0; x < 64; ++x) {
          const bool corner = trial % 5 != 3 || x + 2 * y < 70;
          tile.alpha.at<uchar>(y, x) = corner && cover(random) ? 255 : 0;
        }
      }
      const store::TileImage fast = store::HalveTile(tile), slow = reference(tile);
      ASSERT_EQ(fast.data.type(), slow.data.type());
      EXPECT_EQ(cv::norm(fast.data, slow.data, cv::NORM_INF), 0.0) << "trial " << trial;
      EXPECT_EQ(cv::norm(fast.alpha, slow.alpha, cv::NORM_INF), 0.0) << "trial " << trial;
    }
  }
}

// The direct decoder's prefix sums (SSE2 in steps of 16 or 8 samples, then a scalar tail) against
// the plain running sum, over lengths around the vector widths, with wrap-around.
TEST(TileStoreTest, PredictorUndoneAsARunningSum) {
  std::mt19937 random(11);
  for (int n : {0, 1, 7, 8, 9, 15, 16, 17, 31, 32, 33, 100, 256, 300}) {
    std::vector<uint8_t> bytes(n);
    std::vector<uint16_t> words(n);
    for (int i = 0; i < n; ++i) {
      bytes[i] = static_cast<uint8_t>(random());
      words[i] = static_cast<uint16_t>(random());
    }
    std::vector<uint8_t> expected8(n);
    std::vector<uint16_t> expected16(n);
    uint32_t sum8 = 0, sum16 = 0;
    for (int i = 0; i < n; ++i) {
      sum8 += bytes[i];
      sum16 += words[i];
      expected8[i] = static_cast<uint8_t>(sum8 & 0xFF);
      expected16[i] = static_cast<uint16_t>(sum16 & 0xFFFF);
    }
    store::UndoHorizontalDifferencing(bytes.data(), n);
    store::UndoHorizontalDifferencing(words.data(), n);
    EXPECT_EQ(bytes, expected8) << "n " << n;
    EXPECT_EQ(words, expected16) << "n " << n;
  }
}

// A tile layout of the direct encoder and decoder tests, and whether it takes the direct path.
struct LayoutCase {
  PixelType type;
  int size;
  std::string compression;
  bool direct;
  // How the store writes such a tile (the CRS of the tests' flight origin).
  store::TileWriteSettings Settings() const {
    store::TileWriteSettings settings;
    settings.type = type;
    settings.compression = compression;
    settings.crs_wkt = LocalFrame(kLat0, kLon0).CrsWkt();
    return settings;
  }
};

// A tile as a mosaic holds: smooth ground with noise (the predictor leaves small differences)
// and a covered disc with a ragged edge, zero outside it.
store::TileImage SyntheticTile(int size, PixelType type, std::mt19937* random) {
  store::TileImage tile = store::EmptyTile(size, type);
  cv::Mat ground(size, size, CV_32F);
  cv::randn(ground, 0, 1);
  cv::GaussianBlur(ground, ground, cv::Size(0, 0), 6);
  cv::normalize(ground, ground, 0, type == PixelType::kByte ? 255 : 60000, cv::NORM_MINMAX);
  cv::Mat noise(size, size, CV_32F);
  cv::randn(noise, 0, type == PixelType::kByte ? 3 : 300);
  ground += noise;
  ground.convertTo(tile.data, tile.data.type());
  std::bernoulli_distribution ragged(0.3);
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      const double r = std::hypot(x - size * 0.4, y - size * 0.6);
      tile.alpha.at<uchar>(y, x) = r < size * 0.45 || (r < size * 0.5 && ragged(*random)) ? 255 : 0;
    }
  }
  tile.data.setTo(0, tile.alpha == 0);
  return tile;
}

// Tiles read back by ReadTile's own decoder (ZSTD blocks, the predictor undone in SSE2) hold the
// same samples and coverage as GDAL's decoding of the same file, for both integer types and tile
// sizes of whole and partial 256-pixel blocks; other layouts (DEFLATE, Float32) go through GDAL.
// A tile cut short, or grown past any tile's size, is an error naming the file, not a crash.
TEST(TileStoreTest, TilesReadBackDirectlyEqualGdalsDecoding) {
  GDALAllRegister();
  const fs::path dir = FreshDir("direct_read");
  std::mt19937 random(3);
  const std::vector<LayoutCase> cases = {
      {PixelType::kByte, 512, "ZSTD", true},     {PixelType::kUInt16, 512, "ZSTD", true},
      {PixelType::kByte, 300, "ZSTD", true},     {PixelType::kUInt16, 300, "ZSTD", true},
      {PixelType::kUInt16, 64, "ZSTD", true},    {PixelType::kUInt16, 512, "DEFLATE", false},
      {PixelType::kFloat32, 256, "ZSTD", false},
  };
  for (const LayoutCase& c : cases) {
    SCOPED_TRACE(std::to_string(c.size) + " " + c.compression + " type " +
                 std::to_string(static_cast<int>(c.type)));
    const store::TileImage tile = SyntheticTile(c.size, c.type, &random);
    const store::TileWriteSettings settings = c.Settings();
    double gt[6];
    store::TileGeoTransform(kGsd, c.size, 0, {-3, 2}, gt);
    const fs::path path = dir / "tile.tif";
    store::WriteTileAtomic(path, tile, gt, settings);

    const int64_t direct_before = store::DirectTileReads();
    const store::TileImage direct = store::ReadTile(path, c.size, c.type);
    EXPECT_EQ(store::DirectTileReads() - direct_before, c.direct ? 1 : 0);
    const store::TileImage by_gdal =
        store::ReadTile(path, c.size, c.type, nullptr, store::TileDecoding::kGdal);
    EXPECT_EQ(store::DirectTileReads() - direct_before, c.direct ? 1 : 0);
    ASSERT_EQ(direct.data.type(), tile.data.type());
    EXPECT_EQ(cv::norm(direct.data, by_gdal.data, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::norm(direct.alpha, by_gdal.alpha, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::norm(direct.data, tile.data, cv::NORM_INF), 0.0);  // Lossless.
    EXPECT_EQ(cv::norm(direct.alpha, tile.alpha, cv::NORM_INF), 0.0);

    if (c.size == 512 && c.type == PixelType::kByte) {
      // Cut short inside the first band's blocks: its block table points past the end.
      const auto full = fs::file_size(path);
      fs::resize_file(path, full / 3);
      GdalErrorCount quiet;
      try {
        store::ReadTile(path, c.size, c.type);
        ADD_FAILURE() << "a truncated tile was read without an error";
      } catch (const OutputError& e) {
        EXPECT_NE(std::string(e.what()).find(path.string()), std::string::npos) << e.what();
        EXPECT_NE(std::string(e.what()).find("Fix:"), std::string::npos) << e.what();
      }
      // Grown far past any tile (a damaged store): refused before it is read into memory.
      fs::resize_file(path, 64 << 20);  // Sparse: no disk taken.
      try {
        store::ReadTile(path, c.size, c.type);
        ADD_FAILURE() << "a 64 MiB tile was read";
      } catch (const OutputError& e) {
        EXPECT_NE(std::string(e.what()).find("more than a tile"), std::string::npos) << e.what();
      }
    }
  }
  fs::remove_all(dir);
}

// Tiles written by WriteTileAtomic's own encoder (the predictor in SSE2, blocks compressed with
// libzstd, libtiff writing the file around them) are the files GDAL writes for the same tile as
// far as any reader sees: the same shape, type, block size, compression, predictor, alpha band,
// geotransform, CRS and samples, read back exactly by GDAL and by ReadTile's own decoder. The
// first tile of a CRS goes through GDAL (its georeferencing tags are copied from it); layouts
// the encoder does not make (DEFLATE, Float32, partial blocks) always do.
TEST(TileStoreTest, TilesWrittenDirectlyEqualGdalsWriting) {
  GDALAllRegister();
  const fs::path dir = FreshDir("direct_write");
  const LocalFrame frame(kLat0, kLon0);
  std::mt19937 random(5);
  const std::vector<LayoutCase> cases = {
      {PixelType::kByte, 512, "ZSTD", true},     {PixelType::kUInt16, 512, "ZSTD", true},
      {PixelType::kByte, 64, "ZSTD", true},      {PixelType::kUInt16, 256, "ZSTD", true},
      {PixelType::kUInt16, 300, "ZSTD", false},  {PixelType::kByte, 512, "DEFLATE", false},
      {PixelType::kFloat32, 256, "ZSTD", false},
  };
  const auto item = [](GDALDatasetH ds, const char* key) {
    const char* value = GDALGetMetadataItem(ds, key, "IMAGE_STRUCTURE");
    return std::string(value ? value : "");
  };
  for (const LayoutCase& c : cases) {
    // Variant 1 has blocks of one value, which the encoder compresses once and then copies: the
    // first block covered with one data value, the last uncovered (one block: uncovered).
    for (int variant = 0; variant < 2; ++variant) {
      SCOPED_TRACE(std::to_string(c.size) + " " + c.compression + " type " +
                   std::to_string(static_cast<int>(c.type)) + " variant " +
                   std::to_string(variant));
      store::TileImage tile = SyntheticTile(c.size, c.type, &random);
      if (variant == 1) {
        const int block = std::min(256, c.size), last = c.size - block;
        tile.data(cv::Rect(0, 0, block, block)).setTo(77);
        tile.alpha(cv::Rect(0, 0, block, block)).setTo(255);
        tile.data(cv::Rect(last, last, block, block)).setTo(0);
        tile.alpha(cv::Rect(last, last, block, block)).setTo(0);
      }
      store::TileWriteSettings settings = c.Settings();
      double gt[6];
      store::TileGeoTransform(kGsd, c.size, 1, {-3, 2}, gt);
      const fs::path direct_path = dir / "direct.tif", gdal_path = dir / "gdal.tif";
      store::WriteTileAtomic(direct_path, tile, gt, settings);  // The first of its kind, maybe.
      const int64_t before = store::DirectTileWrites();
      store::WriteTileAtomic(direct_path, tile, gt, settings);
      EXPECT_EQ(store::DirectTileWrites() - before, c.direct ? 1 : 0);
      // Written again, with every block of one value already compressed: the same bytes.
      const std::string first_bytes = FileBytes(direct_path);
      store::WriteTileAtomic(direct_path, tile, gt, settings);
      EXPECT_TRUE(FileBytes(direct_path) == first_bytes);
      settings.encoding = store::TileEncoding::kGdal;
      store::WriteTileAtomic(gdal_path, tile, gt, settings);
      EXPECT_EQ(store::DirectTileWrites() - before, c.direct ? 2 : 0);

      GDALDatasetH a = GDALOpen(direct_path.c_str(), GA_ReadOnly);
      GDALDatasetH b = GDALOpen(gdal_path.c_str(), GA_ReadOnly);
      ASSERT_NE(a, nullptr);
      ASSERT_NE(b, nullptr);
      EXPECT_EQ(GDALGetRasterXSize(a), c.size);
      EXPECT_EQ(GDALGetRasterYSize(a), c.size);
      ASSERT_EQ(GDALGetRasterCount(a), 2);
      double gta[6], gtb[6];
      ASSERT_EQ(GDALGetGeoTransform(a, gta), CE_None);
      ASSERT_EQ(GDALGetGeoTransform(b, gtb), CE_None);
      for (int k = 0; k < 6; ++k) {
        EXPECT_EQ(gta[k], gt[k]) << k;
        EXPECT_EQ(gtb[k], gt[k]) << k;
      }
      EXPECT_STREQ(GDALGetProjectionRef(a), GDALGetProjectionRef(b));
      OGRSpatialReference expected(frame.CrsWkt().c_str()), got(GDALGetProjectionRef(a));
      EXPECT_TRUE(got.IsSame(&expected));
      for (const char* key : {"COMPRESSION", "PREDICTOR", "INTERLEAVE"}) {
        EXPECT_EQ(item(a, key), item(b, key)) << key;
      }
      for (int band = 1; band <= 2; ++band) {
        GDALRasterBandH ba = GDALGetRasterBand(a, band), bb = GDALGetRasterBand(b, band);
        EXPECT_EQ(GDALGetRasterDataType(ba), GDALGetRasterDataType(bb));
        EXPECT_EQ(GDALGetRasterColorInterpretation(ba), GDALGetRasterColorInterpretation(bb));
        int wa = 0, ha = 0, wb = 0, hb = 0;
        GDALGetBlockSize(ba, &wa, &ha);
        GDALGetBlockSize(bb, &wb, &hb);
        EXPECT_EQ(wa, wb);
        EXPECT_EQ(ha, hb);
        cv::Mat sa(c.size, c.size, CV_64F), sb(c.size, c.size, CV_64F);
        ASSERT_EQ(GDALRasterIO(ba, GF_Read, 0, 0, c.size, c.size, sa.ptr(), c.size, c.size,
                               GDT_Float64, 0, 0),
                  CE_None);
        ASSERT_EQ(GDALRasterIO(bb, GF_Read, 0, 0, c.size, c.size, sb.ptr(), c.size, c.size,
                               GDT_Float64, 0, 0),
                  CE_None);
        EXPECT_EQ(cv::norm(sa, sb, cv::NORM_INF), 0.0) << "band " << band;
      }
      EXPECT_EQ(GDALGetRasterColorInterpretation(GDALGetRasterBand(a, 2)), GCI_AlphaBand);
      GDALClose(a);
      GDALClose(b);
      const int64_t reads = store::DirectTileReads();
      const store::TileImage back = store::ReadTile(direct_path, c.size, c.type);
      const bool readable_directly = c.compression == "ZSTD" && c.type != PixelType::kFloat32;
      EXPECT_EQ(store::DirectTileReads() - reads, readable_directly ? 1 : 0);
      EXPECT_EQ(cv::norm(back.data, tile.data, cv::NORM_INF), 0.0);
      EXPECT_EQ(cv::norm(back.alpha, tile.alpha, cv::NORM_INF), 0.0);
    }
  }
  // The predictor both ways, at every row length around the vector width.
  for (int n = 1; n <= 40; ++n) {
    std::vector<uint8_t> bytes(static_cast<size_t>(n)), diff8(bytes.size());
    std::vector<uint16_t> words(static_cast<size_t>(n)), diff16(words.size());
    for (int i = 0; i < n; ++i) {
      bytes[static_cast<size_t>(i)] = static_cast<uint8_t>(random());
      words[static_cast<size_t>(i)] = static_cast<uint16_t>(random());
    }
    store::HorizontalDifferencing(bytes.data(), diff8.data(), n);
    store::HorizontalDifferencing(words.data(), diff16.data(), n);
    EXPECT_EQ(diff8[0], bytes[0]);
    if (n > 1) {
      EXPECT_EQ(diff16[1], static_cast<uint16_t>(words[1] - words[0]));
    }
    store::UndoHorizontalDifferencing(diff8.data(), n);
    store::UndoHorizontalDifferencing(diff16.data(), n);
    EXPECT_EQ(diff8, bytes) << n;
    EXPECT_EQ(diff16, words) << n;
  }
  fs::remove_all(dir);
}

// A tile written again copies the compressed blocks that did not change from its file instead
// of encoding them (a publish rewrites a tile whole when any part of it was painted; an overview
// tile changes by the quadrants of its changed children): the file is the one a full encoding
// gives, byte for byte. A file at the path that is not the one the layout describes (replaced
// by another writer) is not copied from.
TEST(TileStoreTest, UnchangedBlocksAreCopiedFromTheTilesFile) {
  GDALAllRegister();
  const fs::path dir = FreshDir("copied_blocks");
  const LocalFrame frame(kLat0, kLon0);
  std::mt19937 random(11);
  for (const PixelType type : {PixelType::kByte, PixelType::kUInt16}) {
    SCOPED_TRACE(GdalTypeNameOf(type));
    store::TileWriteSettings settings;
    settings.type = type;
    settings.crs_wkt = frame.CrsWkt();
    double gt[6];
    store::TileGeoTransform(kGsd, 512, 0, {4, -1}, gt);
    const fs::path path = dir / "tile.tif", whole = dir / "whole.tif";
    store::TileImage tile = SyntheticTile(512, type, &random);
    store::WriteTileAtomic(path, tile, gt, settings);  // The first of its kind goes through GDAL.
    store::TileFileLayout layout;
    store::WriteTileAtomic(path, tile, gt, settings, nullptr, &layout);
    ASSERT_EQ(layout.offsets.size(), 8u);  // 4 blocks, 2 bands.
    // Block 2 (bottom left) painted: 3 blocks copied, 1 encoded.
    tile.data(cv::Rect(10, 300, 50, 40)).setTo(type == PixelType::kByte ? 201 : 40001);
    tile.alpha(cv::Rect(10, 300, 50, 40)).setTo(255);
    const store::BlockMask changed = store::BlocksOverlapping(cv::Rect(10, 300, 50, 40), 512);
    EXPECT_EQ(changed, store::BlockMask{4});
    const int64_t copied = store::BlocksCopied(), encoded = store::BlocksEncoded();
    const store::TileReuse reuse{&layout, changed};
    store::TileFileLayout next;
    store::WriteTileAtomic(path, tile, gt, settings, &reuse, &next);
    EXPECT_EQ(store::BlocksCopied() - copied, 3);
    EXPECT_EQ(store::BlocksEncoded() - encoded, 1);
    store::WriteTileAtomic(whole, tile, gt, settings);
    EXPECT_TRUE(FileBytes(path) == FileBytes(whole));
    const store::TileImage back =
        store::ReadTile(path, 512, type, nullptr, store::TileDecoding::kGdal);
    EXPECT_EQ(cv::norm(back.data, tile.data, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::norm(back.alpha, tile.alpha, cv::NORM_INF), 0.0);
    // Another file put at the path (same size, another inode): every block encoded.
    fs::copy_file(whole, dir / "other.tif", fs::copy_options::overwrite_existing);
    fs::rename(dir / "other.tif", path);
    tile.data(cv::Rect(10, 300, 50, 40)).setTo(7);
    const int64_t copied_before = store::BlocksCopied();
    const store::TileReuse stale{&next, changed};
    store::WriteTileAtomic(path, tile, gt, settings, &stale, nullptr);
    EXPECT_EQ(store::BlocksCopied(), copied_before);
    store::WriteTileAtomic(whole, tile, gt, settings);
    EXPECT_TRUE(FileBytes(path) == FileBytes(whole));
  }
  // In a store: one block of one level-0 tile painted again; its level-1 tile changes by the
  // quadrant of that child. 512-pixel tiles, 2 x 2 of them, overviews with every publish.
  const fs::path store_dir = dir / "s.irmosaic";
  TileStoreOptions options = Options(store_dir, 512);
  options.overview_interval_s = 0.0;
  options.pixel_type = PixelType::kByte;
  auto store = TileStore::Open(options, Georef());
  PaintSquare(store.get(), {0, 0}, 1024, 100.0);
  store->WaitPublished(store->RequestPublish());
  const TileStore::Stats first = store->stats();
  PaintSquare(store.get(), {600, 50}, 10, 200.0);  // Tile (0, 1), its top-left block.
  store->WaitPublished(store->RequestPublish());
  const TileStore::Stats second = store->stats();
  EXPECT_EQ(second.tiles_written - first.tiles_written, 2);  // Level 0 and level 1.
  EXPECT_EQ(second.blocks_copied - first.blocks_copied, 6);
  EXPECT_EQ(second.blocks_encoded - first.blocks_encoded, 2);
  store->Close();
  cv::Mat expected(512, 512, CV_8U, cv::Scalar(100));
  expected(cv::Rect(88, 50, 10, 10)).setTo(200);
  const store::TileImage level0 = store::ReadTile(
      store_dir / "tiles/0/0_1.tif", 512, PixelType::kByte, nullptr, store::TileDecoding::kGdal);
  EXPECT_EQ(cv::norm(level0.data, expected, cv::NORM_INF), 0.0);
  cv::Mat expected_half(512, 512, CV_8U, cv::Scalar(100));
  expected_half(cv::Rect(256 + 44, 25, 5, 5)).setTo(200);
  const store::TileImage level1 = store::ReadTile(
      store_dir / "tiles/1/0_0.tif", 512, PixelType::kByte, nullptr, store::TileDecoding::kGdal);
  EXPECT_EQ(cv::norm(level1.data, expected_half, cv::NORM_INF), 0.0);
  fs::remove_all(dir);
}

// An oblique frame's footprint fills about half of its bounding box: tiles the box reaches but
// the weights do not must not be read back from disk, created, or marked painted.
TEST(TileStoreTest, TilesUnderZeroWeightsAreNotTouched) {
  const fs::path dir = FreshDir("zero_weight") / "s.irmosaic";
  TileStoreOptions options = Options(dir, 64);
  options.max_cached_tiles = 4;
  options.pixel_type = PixelType::kByte;
  auto store = TileStore::Open(options, Georef());
  // Four tiles on disk, then out of memory (the cache holds four tiles).
  PaintSquare(store.get(), {0, 0}, 128, 100);
  store->WaitPublished(store->RequestPublish());
  PaintSquare(store.get(), {1024, 1024}, 128, 50);  // Four more: the first four leave.
  store->WaitPublished(store->RequestPublish());
  const TileStore::Stats before = store->stats();
  // A patch over all four, with weight only in the top-left tile.
  cv::Mat image(128, 128, CV_8U, cv::Scalar(200));
  cv::Mat weight(128, 128, CV_32F, cv::Scalar(0.0f));
  weight(cv::Rect(10, 10, 20, 20)).setTo(1.0f);
  store->Paint(image, weight, {0, 0});
  const TileStore::Stats after = store->stats();
  EXPECT_EQ(after.tile_reloads - before.tile_reloads, 1);
  // A patch whose weights are all 0 over never-painted ground creates no tile.
  store->Paint(image, cv::Mat(128, 128, CV_32F, cv::Scalar(0.0f)), {5000, 5000});
  EXPECT_EQ(store->stats().tile_reloads, after.tile_reloads);
  const int64_t published = store->RequestPublish();
  store->WaitPublished(published);
  EXPECT_EQ(store->stats().tiles_on_disk, 8u);
  cv::Mat read, coverage;
  store->ReadWindow({0, 0, 128, 128}, &read, &coverage);
  EXPECT_EQ(cv::countNonZero(read == 200), 20 * 20);
  EXPECT_EQ(cv::countNonZero(read == 100), 128 * 128 - 20 * 20);
  store->Close();
}

// A publish that fails after it added its tiles to the next manifest (here: mosaic.vrt cannot
// be replaced) leaves the published manifest as it was; the next publish lists every tile
// painted, before, during and after the failure, at every level (the writer's manifest takes
// the published tile sets instead of copying them, and gives back what a failure added).
TEST(TileStoreTest, AFailedPublishTakesBackItsTilesAndTheNextListsThemAll) {
  const fs::path dir = FreshDir("failed_index") / "s.irmosaic";
  TileStoreOptions options = Options(dir, 64);
  options.pixel_type = PixelType::kByte;
  auto store = TileStore::Open(options, Georef());
  const auto level_tiles = [&](size_t level) {
    const nlohmann::json m = nlohmann::json::parse(std::ifstream(dir / "manifest.json"));
    return m["levels"].size() > level ? manifest_json::LevelTiles(m["levels"][level])
                                      : std::set<manifest_json::ManifestTile>{};
  };
  PaintSquare(store.get(), {0, 0}, 128, 100);  // Tiles (0..1, 0..1).
  store->WaitPublished(store->RequestPublish());
  const auto first = level_tiles(0);
  ASSERT_EQ(first.size(), 4u);
  fs::remove(dir / "mosaic.vrt");
  fs::create_directories(dir / "mosaic.vrt" / "blocker");  // rename() onto it fails.
  PaintSquare(store.get(), {256, 0}, 128, 110);  // Tiles (0..1, 4..5), then far away: (20, 20).
  PaintSquare(store.get(), {1280, 1280}, 64, 120);
  EXPECT_THROW(store->WaitPublished(store->RequestPublish()), OutputError);
  EXPECT_EQ(level_tiles(0), first) << "the failed publish changed the published manifest";
  fs::remove_all(dir / "mosaic.vrt");
  PaintSquare(store.get(), {0, 256}, 64, 130);  // Tile (4, 0).
  store->WaitPublished(store->RequestPublish());
  store->Close();
  std::set<manifest_json::ManifestTile> expected = first;
  for (const manifest_json::ManifestTile& t :
       std::set<manifest_json::ManifestTile>{{0, 4}, {0, 5}, {1, 4}, {1, 5}, {20, 20}, {4, 0}}) {
    expected.insert(t);
  }
  EXPECT_EQ(level_tiles(0), expected);
  // Each overview level holds the parents of the level below.
  const size_t levels =
      nlohmann::json::parse(std::ifstream(dir / "manifest.json"))["levels"].size();
  EXPECT_GE(levels, 3u);  // 21 x 21 tiles: overview levels (as many as 64-pixel tiles allow).
  for (size_t level = 1; level < levels; ++level) {
    std::set<manifest_json::ManifestTile> parents;
    for (const auto& [row, col] : level_tiles(level - 1)) {
      parents.insert(
          {row >= 0 ? row / 2 : -((-row + 1) / 2), col >= 0 ? col / 2 : -((-col + 1) / 2)});
    }
    EXPECT_EQ(level_tiles(level), parents) << "level " << level;
  }
  GdalErrorCount errors;
  const Raster all = ReadThroughGdal(dir / "mosaic.vrt", 0);
  ASSERT_FALSE(all.data.empty()) << errors.last;
}

// Overview VRTs of extents the mosaic outgrew stay an hour for readers holding an older
// mosaic.vrt, then go: at the first overview update and at Close's publish (in between at most
// once a minute, since listing the overview folders costs more as the flight grows); the VRTs the
// manifest names and the tiles stay.
TEST(TileStoreTest, StaleOverviewVrtsGoAfterAnHourTheCurrentOnesStay) {
  const fs::path dir = FreshDir("stale_vrts") / "s.irmosaic";
  TileStoreOptions options = Options(dir, 64);
  options.pixel_type = PixelType::kByte;
  auto store = TileStore::Open(options, Georef());
  const auto make_vrt = [&](const std::string& name, std::chrono::minutes age) {
    // Overviews' in tiles/1, level 0's in tiles/ itself.
    const fs::path path = dir / (name.rfind("level0_", 0) == 0 ? "tiles" : "tiles/1") / name;
    fs::create_directories(path.parent_path());
    std::ofstream(path) << "<VRTDataset/>\n";
    fs::last_write_time(path, fs::file_time_type::clock::now() - age);
    return path;
  };
  const fs::path old_one = make_vrt("overview_r0_c0_1x1.vrt", std::chrono::minutes(90));
  const fs::path recent = make_vrt("overview_r0_c0_1x2.vrt", std::chrono::minutes(10));
  const fs::path old_level0 = make_vrt("level0_r0_c0_1x1.vrt", std::chrono::minutes(90));
  const fs::path recent_level0 = make_vrt("level0_r0_c0_1x2.vrt", std::chrono::minutes(10));
  PaintSquare(store.get(), {0, 0}, 192, 100);  // 3 x 3 tiles: two overview levels.
  store->WaitPublished(store->RequestPublish());
  EXPECT_FALSE(fs::exists(old_one)) << "a VRT unused for an hour stayed";
  EXPECT_TRUE(fs::exists(recent)) << "a VRT a reader may still open went";
  EXPECT_FALSE(fs::exists(old_level0)) << "a level-0 VRT unused for an hour stayed";
  EXPECT_TRUE(fs::exists(recent_level0)) << "a level-0 VRT a reader may still open went";
  const nlohmann::json manifest = nlohmann::json::parse(std::ifstream(dir / "manifest.json"));
  std::vector<std::string> current = manifest["overview_vrts"];
  ASSERT_FALSE(current.empty());
  current.push_back(manifest["level0_vrt"]);
  for (const std::string& vrt : current) {
    EXPECT_TRUE(fs::exists(dir / vrt)) << vrt;
    // Stale by age, but named by the manifest: it stays.
    fs::last_write_time(dir / vrt, fs::file_time_type::clock::now() - std::chrono::minutes(90));
  }
  const fs::path later = make_vrt("overview_r0_c0_2x2.vrt", std::chrono::minutes(90));
  PaintSquare(store.get(), {0, 0}, 64, 120);  // Within the minute: only Close's publish cleans.
  store->Close();
  EXPECT_FALSE(fs::exists(later)) << "Close left a VRT unused for an hour";
  for (const std::string& vrt : current) EXPECT_TRUE(fs::exists(dir / vrt)) << vrt;
  EXPECT_TRUE(fs::exists(dir / "tiles/1/0_0.tif"));
}

// Deferred overviews keep the latest image of every tile they owe: however long the interval,
// they must not hold more than 8 x max_cached_tiles of them (halved: a quarter of a tile each)
// after a publish. Past 4 x max_cached_tiles an update starts early, in slices between
// publishes like the clock's: the publish that starts it writes no overview tile, so its frames
// do not wait for the pyramid (until session 33 it did the update itself, 0.6-0.8 s of the
// writer's time at 25 fps, the publish latency's p99). Past 8 x, waiting and under way
// together, a publish does the update itself (a burst, e.g. the final solve's re-renders).
TEST(TileStoreTest, TilesOwedToDeferredOverviewsStayBoundedAndUpdateInSlices) {
  const fs::path dir = FreshDir("owed") / "s.irmosaic";
  TileStoreOptions options = Options(dir, 64);
  options.max_cached_tiles = 8;
  options.overview_interval_s = 3600.0;  // Never due by the clock during the test.
  options.overview_slice_tiles = 8;
  options.pixel_type = PixelType::kByte;
  auto store = TileStore::Open(options, Georef());
  // 200 tiles in a row, 5 per publish: unbounded, 200 would wait.
  size_t most_owed = 0;
  for (int i = 0; i < 200; ++i) {
    PaintSquare(store.get(), {i * 64, 0}, 64, 100 + i % 100);
    if (i % 5 == 4) {
      store->WaitPublished(store->RequestPublish());
      most_owed = std::max(most_owed, store->stats().overview_owed_tiles);
    }
  }
  TileStore::Stats stats = store->stats();
  EXPECT_GT(most_owed, 4 * options.max_cached_tiles);  // Deferred up to the bound at least.
  EXPECT_LE(most_owed, 8 * options.max_cached_tiles);
  EXPECT_GE(stats.overview_updates_early, 3);
  // One slice runs after each publish: these slices keep up, no publish did an update.
  EXPECT_EQ(stats.overview_updates_in_publish, 0);
  EXPECT_GT(stats.overview_slices, 0);
  EXPECT_TRUE(fs::exists(dir / "tiles/1"));  // Before Close.
  // A burst of 80 tiles at once (one Paint spanning them, as a final solve's re-renders or a
  // long footprint can) passes twice the bound in one publish (Paint's back-pressure asks for it
  // and it takes all 80): that publish brings the overviews up to date itself. (Until session 36
  // the burst was 80 one-tile paints, whose back-pressure publishes of 16 tiles outran the slices
  // only while tile writes were slow: with the store's own encoder the slices kept up under ASan.)
  store->Paint(cv::Mat(64, 80 * 64, CV_8U, cv::Scalar(7)),
               cv::Mat(64, 80 * 64, CV_32F, cv::Scalar(1.0f)), {0, 64});
  store->WaitPublished(store->RequestPublish());
  stats = store->stats();
  EXPECT_GE(stats.overview_updates_in_publish, 1);
  EXPECT_LE(stats.overview_owed_tiles, 8 * options.max_cached_tiles);
  store->Close();
  GdalErrorCount errors;
  const Raster level1 = ReadThroughGdal(dir / "mosaic.vrt", 1);
  ASSERT_FALSE(level1.data.empty()) << errors.last;
  EXPECT_EQ(cv::countNonZero(level1.data == 7), 80 * 32 * 32);
  EXPECT_EQ(cv::countNonZero(level1.data == 100 + 99), 2 * 32 * 32);  // Tiles 99 and 199.
}

// Painting while the writer publishes: a publish's snapshot shares the tiles' buffers (copy on
// write), so a tile painted again during its publish must keep the new value, in memory and on
// disk (level 0 and the overviews) once published. scripts/tsan.sh runs this test under
// ThreadSanitizer: a writer that dropped its snapshot outside the lock was reported racing with
// the painter's copy of a shared tile when the copy fell in the publish's overview phase.
// overview_interval_s 0: overviews within every publish; > 0: in slices between publishes.
// PaintKind::kRefresh: the tile is repainted as the optimizer's re-renders are, so a refresh
// slice after each publish writes it (in place) while the painter copies it.
void PaintDuringPublishes(const std::string& name, double overview_interval_s,
                          PaintKind kind = PaintKind::kNew) {
  const fs::path dir = FreshDir(name) / "s.irmosaic";
  TileStoreOptions options = Options(dir, 64);
  options.pixel_type = PixelType::kByte;
  options.overview_interval_s = overview_interval_s;
  options.overview_slice_tiles = 1;
  auto store = TileStore::Open(options, Georef());
  PaintSquare(store.get(), {0, 0}, 512, 1);  // 8 x 8 tiles: overview levels 1 to 3.
  store->WaitPublished(store->RequestPublish());
  // How long publishing one changed tile takes here (sanitizers slow it down).
  const auto start = std::chrono::steady_clock::now();
  PaintSquare(store.get(), {0, 0}, 64, 2);
  store->WaitPublished(store->RequestPublish());
  const auto publish_time = std::chrono::steady_clock::now() - start;
  // Paint tile (0, 0), publish, and paint it again at a moment that sweeps the publish from its
  // start to its end: the second paint copies the tile while the writer still holds it.
  // A refresh slice runs after the publish: the sweep spans both.
  const int sweep = kind == PaintKind::kRefresh ? 2 : 1;
  int last = 0;
  for (int i = 0; i < 40; ++i) {
    PaintSquare(store.get(), {0, 0}, 64, 10 + 2 * i, 1.0f, kind);
    const int64_t generation = store->RequestPublish();
    std::this_thread::sleep_for(publish_time * sweep * (i % 20) / 20);
    last = 11 + 2 * i;
    PaintSquare(store.get(), {0, 0}, 64, last, 1.0f, kind);
    store->WaitPublished(generation);
  }
  store->WaitPublished(store->RequestPublish());
  if (kind == PaintKind::kRefresh) {
    EXPECT_GT(store->stats().refresh_slices, 0) << "no refresh slice ran";
  }
  cv::Mat image, coverage;
  store->ReadWindow({0, 0, 64, 64}, &image, &coverage);
  EXPECT_EQ(cv::countNonZero(image == last), 64 * 64);
  store->Close();
  GdalErrorCount errors;
  for (int level = 0; level <= 3; ++level) {
    const Raster r = ReadThroughGdal(dir / "mosaic.vrt", level);
    ASSERT_FALSE(r.data.empty()) << "level " << level << ": " << errors.last;
    const int side = 64 >> level;  // Tile (0, 0)'s share of the level.
    EXPECT_EQ(cv::countNonZero(r.data(cv::Rect(0, 0, side, side)) == last), side * side)
        << "level " << level;
  }
}

TEST(TileStoreTest, PaintingDuringPublishesKeepsTheLastPaintedValues) {
  PaintDuringPublishes("paint_publish", 0.0);
}

TEST(TileStoreTest, PaintingDuringOverviewSlicesKeepsTheLastPaintedValues) {
  PaintDuringPublishes("paint_slices", 0.001);
}

TEST(TileStoreTest, PaintingDuringRefreshSlicesKeepsTheLastPaintedValues) {
  PaintDuringPublishes("paint_refresh", 0.001, PaintKind::kRefresh);
}

// Everything a store holds in tile (row, col) of a level-0 window read through GDAL is `value`.
void ExpectTileHolds(const Raster& r, int tile, int row, int col, int value) {
  ASSERT_FALSE(r.data.empty());
  const cv::Rect area(col * tile, row * tile, tile, tile);
  ASSERT_TRUE((area & cv::Rect(0, 0, r.data.cols, r.data.rows)) == area);
  EXPECT_EQ(cv::countNonZero(r.data(area) == value), tile * tile)
      << "tile (" << row << ", " << col << ") should hold " << value;
}

// Waits (at most 60 s) until refresh slices wrote at least `tiles` tiles since `before`; returns
// the store's stats then.
TileStore::Stats WaitForRefreshWrites(TileStore* store, const TileStore::Stats& before,
                                      int64_t tiles) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  while (store->stats().refresh_tiles_written - before.refresh_tiles_written < tiles &&
         std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  return store->stats();
}

// Refreshes (PaintKind::kRefresh, the optimizer's re-renders) of tiles on disk are not written
// by the publish after them but by refresh slices right after it, in place: the generation
// stays, and the publish carries only new content (and refreshes of tiles not yet on disk, which
// need listing). Close writes what still waits.
TEST(TileStoreTest, RefreshedTilesAreWrittenInSlicesAfterThePublish) {
  constexpr int kTile = 64;
  const fs::path dir = FreshDir("refresh") / "s.irmosaic";
  TileStoreOptions options = Options(dir, kTile);
  options.pixel_type = PixelType::kByte;
  options.refresh_slice_tiles = 1;
  auto store = TileStore::Open(options, Georef());
  PaintSquare(store.get(), {0, 0}, 2 * kTile, 1);  // Tiles (0, 0), (0, 1), (1, 0), (1, 1).
  store->WaitPublished(store->RequestPublish());
  const TileStore::Stats before = store->stats();
  // (0, 0) and (0, 1) refreshed; (1, 0) painted anew; (0, 2), not on disk yet, refreshed.
  const auto paint = [&](cv::Rect area, int value, PaintKind kind) {
    store->Paint(cv::Mat(area.size(), CV_8U, cv::Scalar(value)),
                 cv::Mat(area.size(), CV_32F, cv::Scalar(1.0f)), area.tl(), kind);
  };
  paint({0, 0, 2 * kTile, kTile}, 2, PaintKind::kRefresh);
  paint({0, kTile, kTile, kTile}, 3, PaintKind::kNew);
  paint({2 * kTile, 0, kTile, kTile}, 4, PaintKind::kRefresh);
  EXPECT_EQ(store->stats().refresh_waiting, 2u);
  const int64_t generation = store->RequestPublish();
  store->WaitPublished(generation);
  // The slices follow the publish, one tile each.
  TileStore::Stats after = WaitForRefreshWrites(store.get(), before, 2);
  EXPECT_EQ(after.refresh_tiles_written - before.refresh_tiles_written, 2);
  EXPECT_EQ(after.refresh_slices - before.refresh_slices, 2);
  EXPECT_EQ(after.refresh_waiting, 0u);
  // At level 0 the publish wrote (1, 0) and (0, 2) only; the slices the two refreshed tiles.
  EXPECT_EQ((after.tiles_written - after.overview_tiles_written) -
                (before.tiles_written - before.overview_tiles_written),
            4);
  EXPECT_EQ(store->published_generation(), generation);
  {
    const Raster r = ReadThroughGdal(dir / "mosaic.vrt");
    EXPECT_EQ(r.generation, generation);
    ExpectTileHolds(r, kTile, 0, 0, 2);
    ExpectTileHolds(r, kTile, 0, 1, 2);
    ExpectTileHolds(r, kTile, 1, 0, 3);
    ExpectTileHolds(r, kTile, 1, 1, 1);
    ExpectTileHolds(r, kTile, 0, 2, 4);
  }
  // A refresh with nothing new still asks for a publish (the slices follow publishes), and one
  // left waiting is written by Close.
  paint({kTile, kTile, kTile, kTile}, 5, PaintKind::kRefresh);
  EXPECT_GT(store->RequestPublish(), generation);
  paint({0, 0, kTile, kTile}, 6, PaintKind::kRefresh);
  store->Close();
  const Raster r = ReadThroughGdal(dir / "mosaic.vrt");
  ExpectTileHolds(r, kTile, 1, 1, 5);
  ExpectTileHolds(r, kTile, 0, 0, 6);
}

// refresh_quiet_publishes: a refreshed tile is written once that many publishes passed without
// it being painted, so a tile repainted at every publish (re-renders of neighbouring frames)
// waits, and is written once, with its last values, when they stop.
TEST(TileStoreTest, ARefreshedTileWaitsForItsQuietPublishesAndIsWrittenOnce) {
  constexpr int kTile = 64;
  const fs::path dir = FreshDir("refresh_quiet") / "s.irmosaic";
  TileStoreOptions options = Options(dir, kTile);
  options.pixel_type = PixelType::kByte;
  options.refresh_slice_tiles = 1;
  options.refresh_quiet_publishes = 3;
  // Each publish reports the refresh slices that ran since the one before: what ran between
  // two publishes, known without racing the writer (a slice may run right after a publish,
  // before or after this thread looks at the stats).
  std::mutex mu;
  std::map<int64_t, int> slices_before;  // generation -> refresh slices since the previous one
  options.on_publish = [&](const PublishReport& report) {
    std::lock_guard<std::mutex> lock(mu);
    slices_before[report.generation] = report.refresh_slices;
  };
  const auto slices_before_generation = [&](int64_t generation) {
    std::lock_guard<std::mutex> lock(mu);
    const auto it = slices_before.find(generation);
    return it == slices_before.end() ? -1 : it->second;
  };
  auto store = TileStore::Open(options, Georef());
  PaintSquare(store.get(), {0, 0}, kTile, 1);
  store->WaitPublished(store->RequestPublish());
  const TileStore::Stats before = store->stats();
  // Repainted before each publish: never quiet. A slice ready after publish k runs before
  // publish k + 1 (slices take their turn first), so none ran by the time the next is out.
  for (int round = 0; round < 4; ++round) {
    PaintSquare(store.get(), {0, 0}, kTile, 10 + round, 1.0f, PaintKind::kRefresh);
    store->WaitPublished(store->RequestPublish());
    EXPECT_EQ(store->stats().refresh_tiles_written, before.refresh_tiles_written) << round;
    EXPECT_EQ(store->stats().refresh_waiting, 1u) << round;
  }
  // Unpainted: last painted before the fourth round's publish, it is ready after the third
  // publish from there (counting that one). No slice runs after the fourth round's publish or
  // after the first quiet one: the publishes after them report none.
  int64_t quiet_generation = 0;
  for (int quiet = 1; quiet < 3; ++quiet) {
    quiet_generation = store->RequestPublish();
    store->WaitPublished(quiet_generation);
    EXPECT_EQ(slices_before_generation(quiet_generation), 0) << quiet;
  }
  // Written once, with the last values, by the slice after the second quiet publish. Slices
  // take their turn before the next publish, so a publish of new content (another tile)
  // reports it.
  PaintSquare(store.get(), {0, 2 * kTile}, kTile, 50);
  const int64_t next = store->RequestPublish();
  ASSERT_GT(next, quiet_generation);
  store->WaitPublished(next);
  EXPECT_EQ(slices_before_generation(next), 1);
  const TileStore::Stats after = store->stats();
  EXPECT_EQ(after.refresh_tiles_written - before.refresh_tiles_written, 1);
  EXPECT_EQ(after.refresh_waiting, 0u);
  // Level 0: the refreshed tile once, and the new one.
  EXPECT_EQ(after.tiles_written - after.overview_tiles_written,
            before.tiles_written - before.overview_tiles_written + 2);
  ExpectTileHolds(ReadThroughGdal(dir / "mosaic.vrt"), kTile, 0, 0, 13);
  store->Close();
}

// What each publish did and when (TileStoreOptions::on_publish), the figures bench/flight_bench
// traces a frame's latency with: its tiles, the overview update inside it, the slices before it,
// and a finish that is the time PublishedAt gives; delivered before WaitPublished returns.
TEST(TileStoreTest, PublishReportsSayWhatEachPublishDidAndWhen) {
  constexpr int kTile = 64;
  const fs::path dir = FreshDir("reports") / "s.irmosaic";
  TileStoreOptions options = Options(dir, kTile);
  options.pixel_type = PixelType::kByte;
  options.refresh_slice_tiles = 1;
  std::mutex mu;
  std::vector<PublishReport> reports;
  options.on_publish = [&](const PublishReport& report) {
    std::lock_guard<std::mutex> lock(mu);
    reports.push_back(report);
  };
  auto store = TileStore::Open(options, Georef());
  const auto last_report = [&] {
    std::lock_guard<std::mutex> lock(mu);
    return reports.empty() ? PublishReport{} : reports.back();
  };
  // 3 x 3 tiles; overview_interval_s 0: the overviews (and frames.gpkg) inside each publish.
  PaintSquare(store.get(), {0, 0}, 3 * kTile, 1);
  FrameRecord record;
  record.index = 7;
  record.footprint_m = {Eigen::Vector2d(0, 0), {10, 0}, {10, -10}, {0, -10}};
  store->PutFrameRecord(record);
  const auto asked = std::chrono::steady_clock::now();
  const int64_t first = store->RequestPublish();
  store->WaitPublished(first);
  PublishReport r = last_report();
  EXPECT_EQ(r.generation, first);
  EXPECT_FALSE(r.failed);
  EXPECT_EQ(r.level0_tiles, 9);
  EXPECT_EQ(r.refreshed_tiles, 0);
  EXPECT_TRUE(r.overview_update);
  EXPECT_TRUE(r.overview_update_in_publish);
  EXPECT_FALSE(r.overview_update_early);
  EXPECT_GT(r.overview_tiles, 0);
  EXPECT_EQ(r.overview_tiles, store->stats().overview_tiles_written);
  EXPECT_TRUE(r.frames_gpkg);  // It had a record to write.
  EXPECT_GE(r.first_request, asked);
  EXPECT_LE(r.first_request, r.last_request);
  EXPECT_LE(r.last_request, r.started);
  EXPECT_LE(r.started, r.finished);
  ASSERT_TRUE(store->PublishedAt(first).has_value());
  EXPECT_EQ(*store->PublishedAt(first), r.finished);
  const double wall_ms = std::chrono::duration<double, std::milli>(r.finished - r.started).count();
  EXPECT_GT(r.cpu_ms, 0.0);
  EXPECT_LE(r.cpu_ms, wall_ms + 1.0);
  EXPECT_GE(r.run_queue_ms, 0.0);
  EXPECT_LE(r.run_queue_ms, wall_ms + 1.0);
  EXPECT_GT(r.index_ms, 0.0);
  EXPECT_LE(r.index_ms, wall_ms);
  EXPECT_EQ(r.refresh_slices + r.overview_slices, 0);

  // One tile painted anew and one refreshed: the publish writes the new one; the refreshed one
  // goes in a slice after it, which the next publish's report counts.
  PaintSquare(store.get(), {0, 0}, kTile, 2);
  PaintSquare(store.get(), {kTile, 0}, kTile, 3, 1.0f, PaintKind::kRefresh);
  const TileStore::Stats before = store->stats();
  const int64_t second = store->RequestPublish();
  store->WaitPublished(second);
  r = last_report();
  EXPECT_EQ(r.generation, second);
  EXPECT_EQ(r.level0_tiles, 1);
  EXPECT_FALSE(r.frames_gpkg);  // No record since.
  WaitForRefreshWrites(store.get(), before, 1);
  PaintSquare(store.get(), {0, kTile}, kTile, 4);
  const int64_t third = store->RequestPublish();
  store->WaitPublished(third);
  r = last_report();
  EXPECT_EQ(r.generation, third);
  EXPECT_EQ(r.level0_tiles, 1);
  EXPECT_EQ(r.refresh_slices, 1);
  EXPECT_EQ(r.overview_slices, 0);
  EXPECT_GT(r.slices_ms, 0.0);
  {
    std::lock_guard<std::mutex> lock(mu);
    EXPECT_EQ(reports.size(), 3u) << "one report per publish";
  }
  store->Close();

  // A callback that throws does not stop the writer: the publishes go on.
  const fs::path other = FreshDir("reports_throw") / "s.irmosaic";
  TileStoreOptions throwing = Options(other, kTile);
  throwing.pixel_type = PixelType::kByte;
  throwing.on_publish = [](const PublishReport&) { throw std::runtime_error("diagnostics"); };
  auto second_store = TileStore::Open(throwing, Georef());
  for (int k = 0; k < 2; ++k) {
    PaintSquare(second_store.get(), {k * kTile, 0}, kTile, 5 + k);
    const int64_t generation = second_store->RequestPublish();
    second_store->WaitPublished(generation);
    EXPECT_EQ(second_store->published_generation(), generation);
  }
  second_store->Close();
  ExpectTileHolds(ReadThroughGdal(other / "mosaic.vrt"), kTile, 0, 1, 6);
}

// More refreshed tiles waiting than max_cached_tiles (they stay in memory until written): the
// publish takes the least recently painted of them, leaving refresh_slice_tiles fewer than the
// bound waiting (it took them all until session 33: a burst in one publish, the latency's tail);
// slices write the rest. refresh_slice_tiles 0: every publish takes every refresh.
TEST(TileStoreTest, RefreshedTilesGoWithThePublishBeyondTheBoundOrWhenSlicesAreOff) {
  constexpr int kTile = 64;
  for (const int slice_tiles : {1, 0}) {
    SCOPED_TRACE("refresh_slice_tiles " + std::to_string(slice_tiles));
    const fs::path dir = FreshDir("refresh_bound_" + std::to_string(slice_tiles)) / "s.irmosaic";
    TileStoreOptions options = Options(dir, kTile);
    options.pixel_type = PixelType::kByte;
    options.max_cached_tiles = 4;
    options.refresh_slice_tiles = slice_tiles;
    auto store = TileStore::Open(options, Georef());
    // One row of 6 tiles (fewer than twice the bound: painting does not wait for the writer),
    // refreshed from left to right.
    const cv::Size row(6 * kTile, kTile);
    store->Paint(cv::Mat(row, CV_8U, cv::Scalar(1)), cv::Mat(row, CV_32F, cv::Scalar(1.0f)),
                 {0, 0});
    store->WaitPublished(store->RequestPublish());
    for (int col = 0; col < 6; ++col) {
      store->Paint(cv::Mat(kTile, kTile, CV_8U, cv::Scalar(7)),
                   cv::Mat(kTile, kTile, CV_32F, cv::Scalar(1.0f)), {col * kTile, 0},
                   PaintKind::kRefresh);
    }
    EXPECT_EQ(store->stats().refresh_waiting, slice_tiles > 0 ? 6u : 0u);
    const int64_t generation = store->RequestPublish();
    store->WaitPublished(generation);
    // The publish took the 3 least recently painted (6 - (4 - 1)); slices may have taken some
    // of the others since.
    EXPECT_LE(store->stats().refresh_waiting, slice_tiles > 0 ? 3u : 0u);
    if (slice_tiles > 0) {
      // The publish's generation showed the first three refreshed (tiles replaced in place by a
      // slice show at once, so only these are certain).
      const Raster r = ReadThroughGdal(dir / "mosaic.vrt");
      for (int col = 0; col < 3; ++col) ExpectTileHolds(r, kTile, 0, col, 7);
    }
    // The other 3 go by refresh slices (the publish took all 6 until session 33). A slice takes
    // its tiles off the waiting count before it writes them: wait for the count written.
    const int64_t by_slices = slice_tiles > 0 ? 3 : 0;
    const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(30);
    while (
        (store->stats().refresh_waiting > 0 || store->stats().refresh_tiles_written < by_slices) &&
        std::chrono::steady_clock::now() < end) {
      store->RequestPublish();
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    }
    EXPECT_EQ(store->stats().refresh_waiting, 0u);
    EXPECT_EQ(store->stats().refresh_tiles_written, by_slices);
    store->WaitPublished(store->RequestPublish());
    const Raster r = ReadThroughGdal(dir / "mosaic.vrt");
    for (int col = 0; col < 6; ++col) ExpectTileHolds(r, kTile, 0, col, 7);
    store->Close();
  }
}

// Publishes until the store's overviews are up to date (a client's periodic RequestPublish starts
// an owed update); false after `timeout`.
bool WaitForOverviews(TileStore* store, std::chrono::seconds timeout = std::chrono::seconds(120)) {
  const auto end = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < end) {
    if (!store->stats().overviews_pending) return true;
    store->RequestPublish();
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return false;
}

// Every level of the store's mosaic.vrt over its first `side` level-0 pixels holds `value`.
void ExpectLevelsHold(const fs::path& dir, int levels, int side, int value) {
  GdalErrorCount errors;
  for (int level = 0; level <= levels; ++level) {
    const Raster r = ReadThroughGdal(dir / "mosaic.vrt", level);
    ASSERT_FALSE(r.data.empty()) << "level " << level << ": " << errors.last;
    const int n = side >> level;
    ASSERT_GE(r.data.cols, n) << "level " << level;
    EXPECT_EQ(cv::countNonZero(r.data(cv::Rect(0, 0, n, n)) == value), n * n)
        << "level " << level << ", value " << value;
  }
}

// Live (overview_interval_s > 0), the pyramid is brought up to date between publishes in slices
// of at most overview_slice_tiles tiles, and a publish asked for meanwhile goes before the rest
// of the update: a frame's publish waits for one slice, not for the pyramid.
TEST(TileStoreTest, LiveOverviewUpdatesRunInSlicesAndPublishesGoFirst) {
  const fs::path dir = FreshDir("slices") / "s.irmosaic";
  TileStoreOptions options = Options(dir, 64);
  options.pixel_type = PixelType::kByte;
  options.overview_interval_s = 0.001;
  options.overview_slice_tiles = 1;
  options.max_cached_tiles = 2048;
  auto store = TileStore::Open(options, Georef());
  // 16 x 16 tiles: levels 1 to 3 (the most a 64-pixel tile allows), 64 + 16 + 4 = 84 tiles.
  constexpr int kSide = 16 * 64, kLevels = 3, kOverviewTiles = 84;
  PaintSquare(store.get(), {0, 0}, kSide, 1);
  store->WaitPublished(store->RequestPublish());
  ASSERT_TRUE(WaitForOverviews(store.get()));
  // Up to date without a Close: the update ended by itself and its new tiles are listed.
  ExpectLevelsHold(dir, kLevels, kSide, 1);

  // The levels exist now: the next update of every tile runs one tile per slice.
  TileStore::Stats before = store->stats();
  std::this_thread::sleep_for(std::chrono::milliseconds(5));  // Past the interval.
  PaintSquare(store.get(), {0, 0}, kSide, 2);
  store->WaitPublished(store->RequestPublish());
  TileStore::Stats after = store->stats();
  EXPECT_LT(after.overview_tiles_written - before.overview_tiles_written, kOverviewTiles)
      << "the publish waited for the whole pyramid";
  ASSERT_TRUE(WaitForOverviews(store.get()));
  after = store->stats();
  EXPECT_EQ(after.overview_tiles_written - before.overview_tiles_written, kOverviewTiles);
  EXPECT_EQ(after.overview_slices - before.overview_slices, kOverviewTiles);
  ExpectLevelsHold(dir, kLevels, kSide, 2);

  // A publish asked for during an update is published before the update ends, and the update
  // goes on after it to the newest values.
  before = store->stats();
  std::this_thread::sleep_for(std::chrono::milliseconds(5));
  PaintSquare(store.get(), {0, 0}, kSide, 3);
  store->WaitPublished(store->RequestPublish());  // Starts the update of all 84 tiles.
  PaintSquare(store.get(), {0, 0}, 64, 4);
  store->WaitPublished(store->RequestPublish());
  after = store->stats();
  EXPECT_LT(after.overview_slices - before.overview_slices, kOverviewTiles)
      << "the second publish waited for the update to end";
  EXPECT_EQ(ReadThroughGdal(dir / "mosaic.vrt").data.at<float>(0, 0), 4.0f);
  ASSERT_TRUE(WaitForOverviews(store.get()));
  {
    GdalErrorCount errors;
    for (int level = 0; level <= kLevels; ++level) {
      const Raster r = ReadThroughGdal(dir / "mosaic.vrt", level);
      ASSERT_FALSE(r.data.empty()) << "level " << level << ": " << errors.last;
      const int n = 64 >> level;  // Tile (0, 0)'s share of the level.
      EXPECT_EQ(cv::countNonZero(r.data(cv::Rect(0, 0, n, n)) == 4), n * n) << "level " << level;
    }
  }

  // Close right after a publish that started an update, with nothing painted since: Close
  // still brings every level up to date.
  std::this_thread::sleep_for(std::chrono::milliseconds(5));
  PaintSquare(store.get(), {0, 0}, kSide, 5);
  store->WaitPublished(store->RequestPublish());
  store->Close();
  ExpectLevelsHold(dir, kLevels, kSide, 5);
}

TEST(TileStoreTest, BadPathsAreOutputErrorsNamingThePath) {
  const fs::path dir = FreshDir("badpath");
  std::ofstream(dir / "a_file") << "x";
  try {
    TileStore::Open(Options(dir / "a_file" / "s.irmosaic"), Georef());
    FAIL();
  } catch (const OutputError& e) {
    EXPECT_NE(std::string(e.what()).find((dir / "a_file").string()), std::string::npos);
  }
  // A folder the user may not write to: drop root rights in a child process if we have them.
  const fs::path locked = dir / "locked";
  fs::create_directories(locked);
  ::chmod(locked.c_str(), 0555);
  const pid_t child = fork();
  if (child == 0) {
    if (::geteuid() == 0 && (::setgid(65534) != 0 || ::setuid(65534) != 0)) _exit(10);
    try {
      TileStore::Open(Options(locked / "s.irmosaic"), Georef());
      _exit(1);
    } catch (const OutputError& e) {
      _exit(std::string(e.what()).find(locked.string()) != std::string::npos ? 0 : 2);
    } catch (...) {
      _exit(3);
    }
  }
  int status = 0;
  waitpid(child, &status, 0);
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0);
}

TEST(TileStoreTest, DiskFullIsAnOutputErrorAndThePublishedStateSurvives) {
  const fs::path dir = FreshDir("diskfull") / "s.irmosaic";
  int fds[2];
  ASSERT_EQ(pipe(fds), 0);
  const pid_t child = fork();
  if (child == 0) {
    close(fds[0]);
    int code = 1;
    std::string message;
    try {
      auto store = TileStore::Open(Options(dir), Georef());
      PaintSquare(store.get(), {0, 0}, 512, 500);  // 2x2 tiles of a constant: tiny files.
      store->WaitPublished(store->RequestPublish());
      // From now on no file may exceed 32 KiB: a full disk for incompressible tiles.
      signal(SIGXFSZ, SIG_IGN);
      const rlimit limit{32 * 1024, 32 * 1024};
      setrlimit(RLIMIT_FSIZE, &limit);
      cv::Mat noise(512, 512, CV_16U);
      cv::randu(noise, 0, 65535);
      store->Paint(noise, cv::Mat(512, 512, CV_32F, cv::Scalar(1.0f)), {0, 0});
      try {
        store->WaitPublished(store->RequestPublish());
      } catch (const OutputError& e) {
        message = e.what();
        code = 0;
      }
      try {
        store->Close();
        code = 4;  // Close must report the failure too.
      } catch (const OutputError&) {
      }
    } catch (const std::exception& e) {
      message = e.what();
      code = 5;
    }
    if (write(fds[1], message.data(), message.size()) < 0) code = 6;
    _exit(code);
  }
  close(fds[1]);
  std::string message(4096, '\0');
  message.resize(std::max<ssize_t>(0, read(fds[0], message.data(), message.size())));
  close(fds[0]);
  int status = 0;
  waitpid(child, &status, 0);
  ASSERT_TRUE(WIFEXITED(status));
  ASSERT_EQ(WEXITSTATUS(status), 0) << message;
  EXPECT_NE(message.find(dir.string()), std::string::npos) << message;
  // The published state (generation 1, the constant) is intact and complete.
  std::ifstream in(dir / "manifest.json");
  EXPECT_EQ(nlohmann::json::parse(in)["generation"], 1);
  GdalErrorCount errors;
  const Raster vrt = ReadThroughGdal(dir / "mosaic.vrt");
  EXPECT_EQ(cv::countNonZero(vrt.data == 500), 512 * 512);
  EXPECT_EQ(errors.count, 0) << errors.last;
  for (const auto& entry : fs::recursive_directory_iterator(dir)) {
    EXPECT_EQ(entry.path().filename().string().find(".tmp"), std::string::npos)
        << "temporary left behind: " << entry.path();
  }
}

// Writer of the concurrency and crash tests: generation g paints every tile of a growing square
// with the value 1000 + g, so a reader can tell a tile's generation and whether it is whole.
void WriteGenerations(const fs::path& dir, TileStoreOptions::Mode mode, int generations) {
  TileStoreOptions options = Options(dir, 128);
  options.mode = mode;
  auto store = TileStore::Open(options, Georef());
  for (int i = 0; i < generations; ++i) {
    const int64_t next = store->published_generation() + 1;
    const int tiles = 2 + static_cast<int>(std::min<int64_t>(next / 3, 5));
    PaintSquare(store.get(), {-128, -128}, 128 * tiles, 1000.0 + static_cast<double>(next));
    store->PutFrameRecord(Footprint(next, "registered"));
    store->WaitPublished(store->RequestPublish());
  }
  store->Close();
}

// Checks one read of the store by a reader process: every tile whole (one value), no value older
// than the index's generation. Returns a problem, or "" if the read is consistent.
std::string CheckStoreRead(const fs::path& dir, int tile_size) {
  GdalErrorCount errors;
  const Raster vrt = ReadThroughGdal(dir / "mosaic.vrt");
  if (vrt.data.empty() || errors.count) return "GDAL failed: " + errors.last;
  const Raster level1 = ReadThroughGdal(dir / "mosaic.vrt", 1);
  if (errors.count) return "GDAL failed on the overview: " + errors.last;
  for (int y = 0; y < vrt.data.rows; y += tile_size) {
    for (int x = 0; x < vrt.data.cols; x += tile_size) {
      const cv::Rect tile(x, y, tile_size, tile_size);
      double lo = 0, hi = 0;
      const cv::Mat covered = vrt.alpha(tile) > 0;
      if (cv::countNonZero(covered) == 0) continue;
      if (cv::countNonZero(covered) != tile_size * tile_size) return "partly covered tile";
      cv::minMaxLoc(vrt.data(tile), &lo, &hi);
      if (lo != hi) return "torn tile: values " + std::to_string(lo) + ".." + std::to_string(hi);
      if (vrt.generation > 0 && lo < 1000.0 + static_cast<double>(vrt.generation)) {
        return "tile older than the index generation";
      }
    }
  }
  (void)level1;
  // The footprints (updated in place, one SQLite transaction per publish, before the index):
  // never an error, and at least the record of every generation the index had published.
  GDALDataset* frames =
      GDALDataset::Open((dir / "frames.gpkg").c_str(), GDAL_OF_VECTOR | GDAL_OF_READONLY);
  OGRLayer* layer = frames ? frames->GetLayerByName("frames") : nullptr;
  const int64_t records = layer ? layer->GetFeatureCount() : -1;
  if (frames) GDALClose(frames);
  if (layer == nullptr || errors.count) return "frames.gpkg unreadable: " + errors.last;
  if (records < vrt.generation) {
    return "frames.gpkg has " + std::to_string(records) + " records, older than generation " +
           std::to_string(vrt.generation);
  }
  return "";
}

TEST(TileStoreTest, ConcurrentReaderProcessNeverSeesAnErrorOrATornTile) {
  const fs::path dir = FreshDir("concurrent") / "s.irmosaic";
  // The reader's count of reads, in memory shared with the writer: the writer publishes until
  // the reader has read the store at least kReads times beside it (at least 30 generations, at
  // most 3000), so a slow machine lengthens the test instead of failing it. Run as one
  // process with the rest of the binary the reader got only 7 reads in 30 generations.
  constexpr int kReads = 10;
  auto* shared_reads =
      static_cast<std::atomic<int>*>(mmap(nullptr, sizeof(std::atomic<int>), PROT_READ | PROT_WRITE,
                                          MAP_SHARED | MAP_ANONYMOUS, -1, 0));
  ASSERT_NE(shared_reads, MAP_FAILED);
  new (shared_reads) std::atomic<int>(0);
  int fds[2];
  ASSERT_EQ(pipe(fds), 0);
  const pid_t reader = fork();
  if (reader == 0) {
    close(fds[0]);
    GDALAllRegister();
    int reads = 0, problems = 0;
    std::string first_problem;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
    while (!fs::exists(dir / "done") && std::chrono::steady_clock::now() < deadline) {
      if (!fs::exists(dir / "manifest.json")) continue;
      const std::string problem = CheckStoreRead(dir, 128);
      shared_reads->store(++reads);
      if (!problem.empty() && problems++ == 0) first_problem = problem;
    }
    const std::string report =
        std::to_string(reads) + " " + std::to_string(problems) + " " + first_problem;
    if (write(fds[1], report.data(), report.size()) < 0) _exit(2);
    _exit(0);
  }
  close(fds[1]);
  int generations = 0;
  {
    TileStoreOptions options = Options(dir, 128);
    auto store = TileStore::Open(options, Georef());
    while (generations < 30 || (shared_reads->load() < kReads && generations < 3000)) {
      const int64_t next = store->published_generation() + 1;
      const int tiles = 2 + static_cast<int>(std::min<int64_t>(next / 3, 5));
      PaintSquare(store.get(), {-128, -128}, 128 * tiles, 1000.0 + static_cast<double>(next));
      store->PutFrameRecord(Footprint(next, "registered"));
      store->WaitPublished(store->RequestPublish());
      ++generations;
    }
    store->Close();
  }
  std::ofstream(dir / "done") << "";
  std::string report(4096, '\0');
  report.resize(std::max<ssize_t>(0, read(fds[0], report.data(), report.size())));
  close(fds[0]);
  int status = 0;
  waitpid(reader, &status, 0);
  munmap(shared_reads, sizeof(std::atomic<int>));
  int reads = 0, problems = -1;
  std::istringstream(report) >> reads >> problems;
  // Writes of frames.gpkg that found it locked by the reader for a moment and went again
  // (store::WriteFramesGpkg): 3 runs in 60 failed so under load before session 44.
  std::printf(
      "%d reads beside the writer's %d generations; frames.gpkg found locked and written again "
      "%lld times\n",
      reads, generations, static_cast<long long>(store::FramesGpkgBusyRetries()));
  EXPECT_GE(reads, kReads) << "the reader must have overlapped the writer: " << report;
  EXPECT_EQ(problems, 0) << report;
}

// Another program may hold frames.gpkg locked for seconds (a script's transaction, a GIS editing
// the footprints). SQLite answers GDAL's transaction "database is locked" at once then, every
// try (session 45: 55 tries in 5 s failed), and the live writer stopped the run. Now a live
// publish waits a moment and puts the records in manifest.json (frames.pending) instead; they
// reach frames.gpkg with a later update once the lock is gone. The closing publish waits
// longer, then publishes the records in the manifest and Close() says what to do.
TEST(TileStoreTest, AFramesGpkgLockedByAnotherProgramDefersItsRecordsNotThePublish) {
  const fs::path dir = FreshDir("frames_locked") / "s.irmosaic";
  const fs::path gpkg = dir / "frames.gpkg";
  int go[2], told[2];
  ASSERT_EQ(pipe(go), 0);
  ASSERT_EQ(pipe(told), 0);
  // The lock holder, forked before the store starts its threads: for each byte on `go` (the
  // milliseconds to hold, in tenths of a second) it takes frames.gpkg's write lock with a
  // transaction, says 'h', holds it, rolls back, closes the file and says 'r'.
  const pid_t holder = fork();
  if (holder == 0) {
    close(go[1]);
    close(told[0]);
    GDALAllRegister();
    char tenths = 0;
    while (read(go[0], &tenths, 1) == 1) {
      GDALDataset* ds = testing::LockFramesGpkg(gpkg.string());
      char said = ds != nullptr ? 'h' : 'x';
      if (write(told[1], &said, 1) != 1 || said != 'h') _exit(3);
      std::this_thread::sleep_for(std::chrono::milliseconds(100 * tenths));
      testing::UnlockFramesGpkg(ds);
      said = 'r';
      if (write(told[1], &said, 1) != 1) _exit(4);
    }
    _exit(0);
  }
  close(go[0]);
  close(told[1]);
  const auto lock_for = [&](int tenths_of_s) {
    const char byte = static_cast<char>(tenths_of_s);
    char said = 0;
    return write(go[1], &byte, 1) == 1 && read(told[0], &said, 1) == 1 && said == 'h';
  };
  const auto released = [&] {
    char said = 0;
    return read(told[0], &said, 1) == 1 && said == 'r';
  };
  const auto gpkg_indices = [&] {
    std::set<int64_t> indices;
    for (const FrameRecord& r : store::ReadFramesGpkg(gpkg)) indices.insert(r.index);
    return indices;
  };
  const auto pending_indices = [&] {
    std::set<int64_t> indices;
    for (const FrameRecord& r : store::ReadManifest(dir / "manifest.json").frames_pending) {
      indices.insert(r.index);
    }
    return indices;
  };

  auto store = TileStore::Open(Options(dir), Georef());  // overview_interval_s 0: every publish.
  store->PutFrameRecord(Footprint(0, "registered"));
  store->WaitPublished(store->RequestPublish());
  ASSERT_EQ(gpkg_indices(), std::set<int64_t>({0}));

  // 1. A live publish while the lock is held (3 s): published, the record in the manifest.
  ASSERT_TRUE(lock_for(30)) << "the second process could not lock frames.gpkg";
  const int64_t retries_before = store::FramesGpkgBusyRetries();
  store->PutFrameRecord(Footprint(1, "registered"));
  EXPECT_NO_THROW(store->WaitPublished(store->RequestPublish()));
  const std::set<int64_t> in_gpkg_while_locked = gpkg_indices();
  const std::set<int64_t> pending_while_locked = pending_indices();
  const int64_t retries = store::FramesGpkgBusyRetries() - retries_before;
  ASSERT_TRUE(released());
  std::printf("a publish under the lock tried frames.gpkg %lld times, then deferred it\n",
              static_cast<long long>(retries + 1));
  EXPECT_EQ(in_gpkg_while_locked, std::set<int64_t>({0})) << "the holder's lock did not hold";
  EXPECT_EQ(pending_while_locked, std::set<int64_t>({1}));
  EXPECT_GE(retries, 1);
  EXPECT_EQ(store->stats().frames_gpkg_locked, 1);
  // A reader of the store meanwhile: both records (frames.gpkg's and the manifest's).
  EXPECT_EQ(TileStore::OpenReadOnly(dir.string())->FrameRecords().size(), 2u);
  // The lock gone, the next publish moves the record into frames.gpkg.
  store->PutFrameRecord(Footprint(2, "registered"));
  store->WaitPublished(store->RequestPublish());
  EXPECT_EQ(gpkg_indices(), std::set<int64_t>({0, 1, 2}));
  EXPECT_TRUE(pending_indices().empty());

  // 2. Closing while the lock is held past the closing wait (shortened to 0.3 s here): the
  // records are published in the manifest and Close() throws, naming the file and the fix.
  store::SetFramesGpkgClosingLockBudgetMsForTesting(300);
  ASSERT_TRUE(lock_for(15));
  store->PutFrameRecord(Footprint(3, "registered"));
  std::string error;
  try {
    store->Close();
  } catch (const OutputError& e) {
    error = e.what();
  }
  store::SetFramesGpkgClosingLockBudgetMsForTesting(store::kFramesGpkgClosingLockBudgetMs);
  const std::set<int64_t> pending_at_close = pending_indices();
  ASSERT_TRUE(released());
  EXPECT_NE(error.find("frames.gpkg"), std::string::npos) << error;
  EXPECT_NE(error.find("locked"), std::string::npos) << error;
  EXPECT_NE(error.find("Fix:"), std::string::npos) << error;
  EXPECT_EQ(pending_at_close, std::set<int64_t>({3}));
  // A resume takes them and its close writes them to frames.gpkg.
  TileStoreOptions options = Options(dir);
  options.mode = TileStoreOptions::Mode::kResume;
  TileStore::Open(options, Georef())->Close();
  EXPECT_EQ(gpkg_indices(), std::set<int64_t>({0, 1, 2, 3}));
  EXPECT_TRUE(pending_indices().empty());
  close(go[1]);  // The holder's read ends: it exits.
  close(told[0]);
  int status = 0;
  waitpid(holder, &status, 0);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << "holder status " << status;
  // The holder's rolled-back changes are nowhere.
  for (const FrameRecord& r : store::ReadFramesGpkg(gpkg)) EXPECT_EQ(r.status, "registered");
}

TEST(TileStoreTest, KillNineMidPublishLeavesALoadableStoreThatResumes) {
  const fs::path dir = FreshDir("crash") / "s.irmosaic";
  std::mt19937 random(42);
  int temporaries_seen = 0;
  for (int round = 0; round < 6; ++round) {
    const pid_t writer = fork();
    if (writer == 0) {
      try {
        WriteGenerations(
            dir, round == 0 ? TileStoreOptions::Mode::kCreate : TileStoreOptions::Mode::kResume,
            100000);
      } catch (...) {
        _exit(1);
      }
      _exit(0);
    }
    // Let it run into its publishes, then kill it without warning. The first round waits for
    // the first publish (up to 5 minutes) before its random delay: on a loaded machine under
    // ASan the store had not published within 150-550 ms (CI of 5a94093).
    if (round == 0) {
      const auto deadline = std::chrono::steady_clock::now() + std::chrono::minutes(5);
      while (!fs::exists(dir / "manifest.json") && std::chrono::steady_clock::now() < deadline) {
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(150 + random() % 400));
    kill(writer, SIGKILL);
    int status = 0;
    waitpid(writer, &status, 0);
    ASSERT_TRUE(WIFSIGNALED(status)) << "writer ended on its own (status " << status << ")";
    for (const auto& entry : fs::recursive_directory_iterator(dir)) {
      temporaries_seen += entry.path().filename().string().find(".tmp") != std::string::npos;
    }
    ASSERT_TRUE(fs::exists(dir / "manifest.json")) << "round " << round;
    EXPECT_EQ(CheckStoreRead(dir, 128), "") << "round " << round;
  }
  std::cout << "temporaries found after the kills (publishes interrupted): " << temporaries_seen
            << "\n";
  // Resume in this process and finish: the result holds everything, no temporaries left.
  std::ifstream in(dir / "manifest.json");
  const int64_t before = nlohmann::json::parse(in)["generation"];
  WriteGenerations(dir, TileStoreOptions::Mode::kResume, 3);
  std::ifstream again(dir / "manifest.json");
  EXPECT_EQ(nlohmann::json::parse(again)["generation"], before + 3);
  EXPECT_EQ(CheckStoreRead(dir, 128), "");
  for (const auto& entry : fs::recursive_directory_iterator(dir)) {
    EXPECT_EQ(entry.path().filename().string().find(".tmp"), std::string::npos) << entry.path();
  }
}

}  // namespace
}  // namespace irmosaic

namespace irmosaic {
namespace {

// Found by fuzz/store_manifest_fuzzer: a damaged manifest (tile_size 0, a JSON string, a float
// too large for an integer, a field of the wrong type) crashed the reader (division by zero,
// uncaught nlohmann::type_error, undefined float-to-int conversion). Each must be an InputError
// naming manifest.json, for read-only opens and resumes alike.
TEST(TileStoreTest, DamagedManifestIsAnInputErrorNotACrash) {
  const fs::path dir = FreshDir("damaged_manifest");
  TileStore::Open(Options(dir), Georef())->Close();
  std::ifstream in(dir / "manifest.json");
  const nlohmann::json good = nlohmann::json::parse(in);
  in.close();
  auto damaged = [&](const std::function<void(nlohmann::json*)>& edit) {
    nlohmann::json j = good;
    edit(&j);
    return j.dump();
  };
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"tile_size 0", damaged([](nlohmann::json* j) { (*j)["tile_size"] = 0; })},
      {"tile_size -256", damaged([](nlohmann::json* j) { (*j)["tile_size"] = -256; })},
      {"tile_size 1e30", damaged([](nlohmann::json* j) { (*j)["tile_size"] = 1e30; })},
      {"tile_size 100", damaged([](nlohmann::json* j) { (*j)["tile_size"] = 100; })},
      {"format_version 3 (a newer program)",
       damaged([](nlohmann::json* j) { (*j)["format_version"] = 3; })},
      {"gsd_m 0", damaged([](nlohmann::json* j) { (*j)["gsd_m"] = 0.0; })},
      {"generation text", damaged([](nlohmann::json* j) { (*j)["generation"] = "x"; })},
      {"format number", damaged([](nlohmann::json* j) { (*j)["format"] = 5; })},
      {"format_version 1e300", damaged([](nlohmann::json* j) { (*j)["format_version"] = 1e300; })},
      {"format 1, tile index 1e300", damaged([](nlohmann::json* j) {
         *j = manifest_json::AsFormat1(*j);
         (*j)["levels"][0]["tiles"] = {{1e300, 0}};
       })},
      {"format 1, tile index 2^62", damaged([](nlohmann::json* j) {
         *j = manifest_json::AsFormat1(*j);
         (*j)["levels"][0]["tiles"] = {{int64_t{1} << 62, 0}};
       })},
      {"planned_bounds_px empty", damaged([](nlohmann::json* j) {
         (*j)["planned_bounds_px"] = {
             {"col_min", 5}, {"row_min", 0}, {"col_max", 5}, {"row_max", 9}};
       })},
      {"planned_bounds_px 1e300", damaged([](nlohmann::json* j) {
         (*j)["planned_bounds_px"] = {
             {"col_min", -1e300}, {"row_min", 0}, {"col_max", 5}, {"row_max", 9}};
       })},
      {"planned_bounds_px text", damaged([](nlohmann::json* j) {
         (*j)["planned_bounds_px"] = {
             {"col_min", "a"}, {"row_min", 0}, {"col_max", 5}, {"row_max", 9}};
       })},
      {"format 1, tile index 2^64 - 1", damaged([](nlohmann::json* j) {
         *j = manifest_json::AsFormat1(*j);
         (*j)["levels"][0]["tiles"] = {{18446744073709551615ULL, 0}};
       })},
      {"overviews_owed not an array",
       damaged([](nlohmann::json* j) { (*j)["overviews_owed"] = "0_0"; })},
      {"overviews_owed entry of 3 numbers", damaged([](nlohmann::json* j) {
         (*j)["overviews_owed"] = {{0, 0, 0}};
       })},
      {"frames.pending not an array",
       damaged([](nlohmann::json* j) { (*j)["frames"]["pending"] = 3; })},
      {"frames.pending footprint of 3 corners", damaged([](nlohmann::json* j) {
         (*j)["frames"]["pending"] = {{{"index", 0},
                                       {"time_s", 0.0},
                                       {"footprint_m", {{0, 0}, {1, 0}, {1, 1}}},
                                       {"pos_only", false},
                                       {"residual_px", 0.0},
                                       {"inliers", 0},
                                       {"status", "registered"}}};
       })},
      {"frames.pending index -1", damaged([](nlohmann::json* j) {
         (*j)["frames"]["pending"] = {{{"index", -1},
                                       {"time_s", 0.0},
                                       {"footprint_m", {{0, 0}, {1, 0}, {1, 1}, {0, 1}}},
                                       {"pos_only", false},
                                       {"residual_px", 0.0},
                                       {"inliers", 0},
                                       {"status", "registered"}}};
       })},
      {"a JSON string", "\"irmosaic-store\""},
      {"a JSON array", "[1, 2]"},
  };
  for (const auto& [name, text] : cases) {
    std::ofstream(dir / "manifest.json", std::ios::trunc) << text;
    try {
      auto reader = TileStore::OpenReadOnly(dir.string());
      cv::Mat image, coverage;
      reader->ReadWindow(cv::Rect(0, 0, 8, 8), &image, &coverage);
      ADD_FAILURE() << name << ": accepted";
    } catch (const InputError& e) {
      EXPECT_NE(std::string(e.what()).find("manifest.json"), std::string::npos) << name;
    }
    EXPECT_THROW(TileStore::Open(
                     [&] {
                       TileStoreOptions options = Options(dir);
                       options.mode = TileStoreOptions::Mode::kResume;
                       return options;
                     }(),
                     Georef()),
                 InputError)
        << name;
  }
  // The undamaged manifest still opens.
  std::ofstream(dir / "manifest.json", std::ios::trunc) << good.dump();
  EXPECT_EQ(TileStore::OpenReadOnly(dir.string())->published_generation(),
            good["generation"].get<int64_t>());
}

}  // namespace
}  // namespace irmosaic

namespace irmosaic {
namespace {

nlohmann::json ReadJson(const fs::path& path) {
  std::ifstream in(path);
  return nlohmann::json::parse(in);
}

// Tile (row, col) of each tiles/<level>/<row>_<col>.tif, and the number of block VRTs there.
std::set<manifest_json::ManifestTile> TilesOnDisk(const fs::path& level_dir, size_t* blocks) {
  std::set<manifest_json::ManifestTile> tiles;
  for (const auto& entry : fs::directory_iterator(level_dir)) {
    const std::string name = entry.path().filename().string();
    if (name.rfind("block_r", 0) == 0) ++*blocks;
    long long row = 0, col = 0;
    char tail[8] = {};
    if (std::sscanf(name.c_str(), "%lld_%lld.%3s", &row, &col, tail) == 3 &&
        std::string(tail) == "tif") {
      tiles.insert({row, col});
    }
  }
  return tiles;
}

// manifest.json is rewritten at every publish: in format 1 it listed every tile (~40 bytes
// each, ~4 MB for an hour's flight), so each publish cost more as the flight went on. Format 2
// lists blocks of 16 x 16 tiles with a bitmap: about 100 bytes per block holding tiles.
TEST(TileStoreTest, ManifestSizeFollowsTheBlocksNotTheTiles) {
  const fs::path dir = FreshDir("manifest_blocks") / "s.irmosaic";
  constexpr int kTile = 64;
  auto store = TileStore::Open(Options(dir, kTile), Georef());
  // 64 x 40 = 2560 level-0 tiles (10 blocks), in strips with publishes between, as a flight.
  const cv::Size strip(64 * kTile, 8 * kTile);
  for (int row = 0; row < 40; row += 8) {
    store->Paint(cv::Mat(strip, CV_16U, cv::Scalar(1000 + row)),
                 cv::Mat(strip, CV_32F, cv::Scalar(1.0f)), {0, row * kTile});
    store->RequestPublish();
  }
  store->Close();  // Every level published.

  std::ifstream in(dir / "manifest.json");
  const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  nlohmann::ordered_json manifest = nlohmann::ordered_json::parse(text);
  EXPECT_EQ(manifest["format_version"], 2);
  // It lists exactly the tiles on disk, level by level, and as many blocks as the VRT index has.
  size_t blocks = 0, tiles = 0;
  for (const auto& level : manifest["levels"]) {
    const std::string name = std::to_string(level["level"].get<int>());
    size_t level_blocks = 0;
    const auto on_disk = TilesOnDisk(dir / "tiles" / name, &level_blocks);
    EXPECT_EQ(manifest_json::LevelTiles(level), on_disk) << "level " << name;
    EXPECT_EQ(level["blocks"].size(), level_blocks) << "level " << name;
    blocks += level_blocks;
    tiles += on_disk.size();
  }
  EXPECT_GE(tiles, 2560u);
  // Everything but the lists, as written, plus 128 bytes per block: 64 hex digits, two indices
  // (at most 12 characters each) and the layout (one value a line, ~35 bytes). A list of tiles
  // would need ~25-40 bytes per tile: up to 256 of them per block.
  for (auto& level : manifest["levels"]) {
    level.erase("blocks");
    level.erase("tiles");
  }
  const size_t without_lists = manifest.dump(1).size() + 1;
  std::printf("manifest.json: %zu bytes for %zu tiles in %zu blocks (%zu without the lists)\n",
              text.size(), tiles, blocks, without_lists);
  EXPECT_LE(text.size(), without_lists + 128 * blocks);
}

// The bit order docs/store.md gives, on a store: tile (1, 2) is digit 4 (row 1) with value 2
// (column 2 of 0-3 from the most significant bit), tile (-1, -1) the last bit of block (-1, -1).
TEST(TileStoreTest, ManifestBitmapFollowsTheDocumentedBitOrder) {
  const fs::path dir = FreshDir("manifest_bits") / "s.irmosaic";
  auto store = TileStore::Open(Options(dir), Georef());
  PaintSquare(store.get(), {2 * 256 + 10, 1 * 256 + 10}, 8, 100);  // Tile (1, 2).
  PaintSquare(store.get(), {-10, -10}, 8, 200);                    // Tile (-1, -1).
  store->Close();
  const nlohmann::json blocks = ReadJson(dir / "manifest.json")["levels"][0]["blocks"];
  const nlohmann::json expected = {{-1, -1, std::string(63, '0') + "1"},
                                   {0, 0, "00002000" + std::string(56, '0')}};
  EXPECT_EQ(blocks, expected);
}

// A store written before format 2 (tiles listed one by one) still opens and resumes, with the
// same tiles, and its next publish writes format 2.
TEST(TileStoreTest, FormatOneManifestStillOpensAndResumesWithTheSameTiles) {
  const fs::path dir = FreshDir("manifest_v1") / "s.irmosaic";
  {
    auto store = TileStore::Open(Options(dir), Georef());
    PaintSquare(store.get(), {-300, -40}, 700, 1500);  // 4 x 4 tiles around four blocks' corner.
    PaintSquare(store.get(), {5000, 300}, 20, 1600);   // Tile (1, 19): block (0, 1).
    store->Close();
  }
  const nlohmann::json written = ReadJson(dir / "manifest.json");
  const nlohmann::json v1 = manifest_json::AsFormat1(written);
  ASSERT_GE(v1["levels"].size(), 2u);
  std::ofstream(dir / "manifest.json", std::ios::trunc) << v1.dump(1) << "\n";
  const cv::Rect window(-300, -300, 5400, 1100);
  cv::Mat image_v1, coverage_v1;
  TileStore::OpenReadOnly(dir.string())->ReadWindow(window, &image_v1, &coverage_v1);
  EXPECT_EQ(cv::countNonZero(image_v1 == 1500), 700 * 700);
  EXPECT_EQ(cv::countNonZero(image_v1 == 1600), 20 * 20);

  TileStoreOptions resume = Options(dir);
  resume.mode = TileStoreOptions::Mode::kResume;
  {
    auto store = TileStore::Open(resume, Georef());
    EXPECT_EQ(store->published_generation(), written["generation"].get<int64_t>());
    cv::Mat image, coverage;
    store->ReadWindow(window, &image, &coverage);
    EXPECT_EQ(cv::countNonZero(image != image_v1), 0);
    PaintSquare(store.get(), {-6000, 0}, 20, 1700);  // Tile (0, -24): a new block (0, -2).
    store->Close();
  }
  const nlohmann::json after = ReadJson(dir / "manifest.json");
  EXPECT_EQ(after["format_version"], 2);
  std::set<manifest_json::ManifestTile> level0 = manifest_json::LevelTiles(v1["levels"][0]);
  level0.insert({0, -24});
  EXPECT_EQ(manifest_json::LevelTiles(after["levels"][0]), level0);
  for (size_t l = 1; l < v1["levels"].size(); ++l) {  // Overview tiles kept (and one added).
    const auto before = manifest_json::LevelTiles(v1["levels"][l]);
    const auto now = manifest_json::LevelTiles(after["levels"][l]);
    EXPECT_TRUE(std::includes(now.begin(), now.end(), before.begin(), before.end())) << l;
  }
  const Raster vrt = ReadThroughGdal(dir / "mosaic.vrt");
  EXPECT_EQ(cv::countNonZero(vrt.data == 1500), 700 * 700);
  EXPECT_EQ(cv::countNonZero(vrt.data == 1700), 20 * 20);
}

// Format 2's lists damaged or edited: each refused naming manifest.json and the field, by a
// read-only open and by --resume alike, never read in part.
TEST(TileStoreTest, DamagedBlockListIsRefusedNamingTheField) {
  const fs::path dir = FreshDir("manifest_bad_blocks") / "s.irmosaic";
  {
    auto store = TileStore::Open(Options(dir), Georef());
    PaintSquare(store.get(), {0, 0}, 600, 1000);
    store->Close();
  }
  const nlohmann::json good = ReadJson(dir / "manifest.json");
  ASSERT_EQ(good["levels"][0]["blocks"].size(), 1u);
  const std::string bits = good["levels"][0]["blocks"][0][2];
  struct Case {
    std::string name, field;
    std::function<void(nlohmann::json&)> edit;
  };
  auto block = [](nlohmann::json& j) -> nlohmann::json& { return j["levels"][0]["blocks"][0]; };
  const std::vector<Case> cases = {
      {"63 digits", "levels[0].blocks[0]", [&](auto& j) { block(j)[2] = bits.substr(1); }},
      {"65 digits", "levels[0].blocks[0]", [&](auto& j) { block(j)[2] = bits + "0"; }},
      {"upper case", "levels[0].blocks[0]", [&](auto& j) { block(j)[2] = "F" + bits.substr(1); }},
      {"not hex", "levels[0].blocks[0]", [&](auto& j) { block(j)[2] = "g" + bits.substr(1); }},
      {"bitmap a number", "levels[0].blocks[0]", [&](auto& j) { block(j)[2] = 7; }},
      {"no tile", "levels[0].blocks[0]", [&](auto& j) { block(j)[2] = std::string(64, '0'); }},
      {"two values", "levels[0].blocks[0]", [&](auto& j) { block(j).erase(2); }},
      {"an object", "levels[0].blocks[0]",
       [&](auto& j) {
         block(j) = nlohmann::json::object({{"row", 0}});
       }},
      {"listed twice", "levels[0].blocks[1]",
       [&](auto& j) { j["levels"][0]["blocks"].push_back(block(j)); }},
      {"block row 2^62 (x16 x tile size overflows)", "levels[0].blocks[0]",
       [&](auto& j) { block(j)[0] = int64_t{1} << 62; }},
      {"block col 2^36", "levels[0].blocks[0]", [&](auto& j) { block(j)[1] = int64_t{1} << 36; }},
      {"block col -2^36 - 1", "levels[0].blocks[0]",
       [&](auto& j) { block(j)[1] = -(int64_t{1} << 36) - 1; }},
      {"block row 2^64 - 1", "levels[0].blocks[0]",
       [&](auto& j) { block(j)[0] = 18446744073709551615ULL; }},
      {"block row 1e300", "levels[0].blocks[0]", [&](auto& j) { block(j)[0] = 1e300; }},
      {"block row 0.5", "levels[0].blocks[0]", [&](auto& j) { block(j)[0] = 0.5; }},
      {"tiles and blocks", "levels[0]",
       [&](auto& j) {
         j["levels"][0]["tiles"] = nlohmann::json::array({{0, 0}});
       }},
      {"blocks missing", "levels[0].blocks", [&](auto& j) { j["levels"][0].erase("blocks"); }},
      {"blocks an object", "levels[0].blocks",
       [&](auto& j) {
         j["levels"][0]["blocks"] = {{"0", "1"}};
       }},
      {"format 1 holding blocks", "levels[0].tiles", [&](auto& j) { j["format_version"] = 1; }},
      {"a level not an object", "levels[1]", [&](auto& j) { j["levels"][1] = 5; }},
      {"format 3", "format_version", [&](auto& j) { j["format_version"] = 3; }},
  };
  TileStoreOptions resume = Options(dir);
  resume.mode = TileStoreOptions::Mode::kResume;
  for (const Case& c : cases) {
    nlohmann::json j = good;
    c.edit(j);
    std::ofstream(dir / "manifest.json", std::ios::trunc) << j.dump(1);
    const std::string where = "(field '" + c.field + "')";
    for (const bool read_only : {true, false}) {
      try {
        const auto store =
            read_only ? TileStore::OpenReadOnly(dir.string()) : TileStore::Open(resume, Georef());
        ADD_FAILURE() << c.name << ": accepted";
      } catch (const InputError& e) {
        const std::string message = e.what();
        EXPECT_NE(message.find("manifest.json"), std::string::npos) << message;
        EXPECT_NE(message.find(where), std::string::npos) << c.name << ": " << message;
      }
    }
  }
  // More tiles than a reader holds, through full blocks: refused from the bitmaps' count,
  // before any tile is held (the cap counts tiles, not entries).
  nlohmann::json many = good;
  for (int64_t k = 1; k <= 33000; ++k) {
    many["levels"][0]["blocks"].push_back({k / 181, k % 181, std::string(64, 'f')});
  }
  std::ofstream(dir / "manifest.json", std::ios::trunc) << many.dump();
  try {
    const auto store = TileStore::OpenReadOnly(dir.string());
    ADD_FAILURE() << "33,000 full blocks accepted";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("more than 8388608 tiles"), std::string::npos) << e.what();
  }
  std::ofstream(dir / "manifest.json", std::ios::trunc) << good.dump(1);
  EXPECT_EQ(TileStore::OpenReadOnly(dir.string())->published_generation(),
            good["generation"].get<int64_t>());
}

// Found by the kill -9 campaign (scripts/faults.sh): a run killed before its first publish
// left a folder with no manifest that neither --resume, --overwrite nor a new run would take.
// Nothing was published, so --resume (and --overwrite) start afresh; anything that is not the
// skeleton of an interrupted creation is still refused, never deleted.
TEST(TileStoreTest, ResumeOfARunKilledBeforeItsFirstPublishStartsAfresh) {
  const fs::path root = FreshDir("killed_early");
  TileStoreOptions resume = Options(root / "never");  // Killed before the folder was made.
  resume.mode = TileStoreOptions::Mode::kResume;
  TileStore::Open(resume, Georef())->Close();
  EXPECT_TRUE(fs::exists(root / "never" / "manifest.json"));

  const fs::path skeleton = root / "skeleton";  // Killed between mkdir and the first index.
  fs::create_directories(skeleton / "tiles" / "0");
  std::ofstream(skeleton / "frames.gpkg") << "partial";
  std::ofstream(skeleton / ".manifest.json.tmp123") << "{";
  TileStoreOptions options = Options(skeleton);
  EXPECT_THROW(TileStore::Open(options, Georef()), InputError);  // A new run still refuses.
  options.mode = TileStoreOptions::Mode::kResume;
  int64_t closed_generation = -1;
  {
    auto store = TileStore::Open(options, Georef());
    EXPECT_EQ(store->published_generation(), 0);  // A new store: generation 0.
    store->Close();
    closed_generation = store->published_generation();
  }
  EXPECT_TRUE(fs::exists(skeleton / "manifest.json"));
  EXPECT_EQ(TileStore::OpenReadOnly(skeleton.string())->published_generation(), closed_generation);

  const fs::path foreign = root / "foreign";  // Not ours: refused and left alone.
  fs::create_directories(foreign);
  std::ofstream(foreign / "notes.txt") << "keep me";
  TileStoreOptions foreign_options = Options(foreign);
  foreign_options.mode = TileStoreOptions::Mode::kResume;
  EXPECT_THROW(TileStore::Open(foreign_options, Georef()), InputError);
  foreign_options.mode = TileStoreOptions::Mode::kOverwrite;
  EXPECT_THROW(TileStore::Open(foreign_options, Georef()), InputError);
  EXPECT_TRUE(fs::exists(foreign / "notes.txt"));
}

}  // namespace
}  // namespace irmosaic
