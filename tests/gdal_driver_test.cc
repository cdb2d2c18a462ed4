// IRMOSAIC GDAL driver: registered in-process (geometry, values against mosaic.vrt, growth,
// malformed manifests) and loaded as a plug-in by GDAL's own tools (gdalinfo, gdal_translate).
#include <dlfcn.h>
#include <gdal.h>
#include <gdal_alg.h>
#include <gdal_priv.h>
#include <gtest/gtest.h>
#include <ogr_spatialref.h>
#include <ogrsf_frmts.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <nlohmann/json.hpp>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "irmosaic/local_frame.h"
#include "irmosaic/tile_store.h"
#include "irmosaic_driver.h"
#include "manifest_tiles.h"

namespace irmosaic {
namespace {

namespace fs = std::filesystem;
constexpr double kLat0 = 47.2, kLon0 = 8.5, kGsd = 0.5;

fs::path FreshDir(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() /
                       ("irmosaic_gdal_driver_test_" + std::to_string(::getpid()) + "_" + name);
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

void PaintSquare(TileStore* store, cv::Point top_left, int size, double value) {
  cv::Mat image(size, size, CvDepthOf(store->pixel_type()), cv::Scalar(value));
  cv::Mat w(size, size, CV_32F, cv::Scalar(1.0));
  // A gradient so that checksums see the position of every sample.
  for (int r = 0; r < size; ++r) image.row(r) += cv::Scalar(r % 97);
  store->Paint(image, w, top_left);
}

FrameRecord Frame(int64_t index, double time_s) {
  FrameRecord record;
  record.index = index;
  record.time_s = time_s;
  record.footprint_m = {Eigen::Vector2d(0, 0), Eigen::Vector2d(10, 0), Eigen::Vector2d(10, -10),
                        Eigen::Vector2d(0, -10)};
  record.status = "registered";
  return record;
}

// A store of 256-pixel tiles: an L of painted squares over 3 x 3 tiles (some absent), two frames.
std::unique_ptr<TileStore> MakeStore(const fs::path& dir) {
  TileStoreOptions options;
  options.path = dir.string();
  options.tile_size = 256;
  const LocalFrame frame(kLat0, kLon0);
  auto store = TileStore::Open(options, {kLat0, kLon0, kGsd, frame.CrsWkt()});
  PaintSquare(store.get(), {-100, -50}, 300, 1000);
  PaintSquare(store.get(), {300, 300}, 200, 2000);
  store->PutFrameRecord(Frame(0, 10.0));
  store->PutFrameRecord(Frame(1, 10.04));
  store->WaitPublished(store->RequestPublish());
  return store;
}

struct GdalErrors {
  GdalErrors() { CPLPushErrorHandlerEx(&Handler, this); }
  ~GdalErrors() { CPLPopErrorHandler(); }
  static void CPL_STDCALL Handler(CPLErr level, CPLErrorNum, const char* message) {
    auto* self = static_cast<GdalErrors*>(CPLGetErrorHandlerUserData());
    if (level >= CE_Failure) {
      ++self->count;
      self->last = message ? message : "";
    }
  }
  int count = 0;
  std::string last;
};

// Registers the driver compiled into this test before GDAL loads its plug-ins: a gdal_IRMOSAIC.so
// installed in GDAL's plug-in folder (cmake --install) would otherwise register first and the
// tests would exercise that copy, not this build's code. TileStore calls GDALAllRegister too,
// so this must happen before any test runs (the environment below).
void RegisterInProcess() {
  GDALRegister_IRMOSAIC();
  GDALAllRegister();
}

class RegisterFirst : public ::testing::Environment {
 public:
  void SetUp() override { RegisterInProcess(); }
};
[[maybe_unused]] ::testing::Environment* const kRegisterFirst =
    ::testing::AddGlobalTestEnvironment(new RegisterFirst);

GDALDatasetUniquePtr OpenWith(const fs::path& path, const char* driver, bool update = false) {
  RegisterInProcess();
  const char* const allowed[] = {driver, nullptr};
  return GDALDatasetUniquePtr(
      GDALDataset::Open(path.c_str(), GDAL_OF_RASTER | (update ? GDAL_OF_UPDATE : GDAL_OF_READONLY),
                        allowed, nullptr, nullptr));
}

// Opens `path` through IRMOSAIC asking for the given kinds (GDAL_OF_RASTER / GDAL_OF_VECTOR).
GDALDatasetUniquePtr OpenKinds(const fs::path& path, unsigned kinds) {
  RegisterInProcess();
  const char* const allowed[] = {"IRMOSAIC", nullptr};
  return GDALDatasetUniquePtr(
      GDALDataset::Open(path.c_str(), kinds | GDAL_OF_READONLY, allowed, nullptr, nullptr));
}

int Checksum(GDALRasterBand* band) {
  return GDALChecksumImage(band, 0, 0, band->GetXSize(), band->GetYSize());
}

class GdalDriverTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = FreshDir(::testing::UnitTest::GetInstance()->current_test_info()->name()) / "s.irmosaic";
    store_ = MakeStore(dir_);
  }
  void TearDown() override {
    if (store_) store_->Close();
    fs::remove_all(dir_.parent_path());
  }
  fs::path dir_;
  std::unique_ptr<TileStore> store_;
};

TEST_F(GdalDriverTest, MatchesMosaicVrtInGeometryCrsAndEveryLevelsChecksums) {
  auto ours = OpenWith(dir_, "IRMOSAIC");
  auto vrt = OpenWith(dir_ / "mosaic.vrt", "VRT");
  ASSERT_TRUE(ours);
  ASSERT_TRUE(vrt);
  EXPECT_STREQ(ours->GetDriver()->GetDescription(), "IRMOSAIC");
  EXPECT_EQ(ours->GetRasterXSize(), vrt->GetRasterXSize());
  EXPECT_EQ(ours->GetRasterYSize(), vrt->GetRasterYSize());
  EXPECT_EQ(ours->GetRasterXSize(), 3 * 256);  // Tiles -1..1 in both axes.
  double gt_ours[6], gt_vrt[6];
  ASSERT_EQ(ours->GetGeoTransform(gt_ours), CE_None);
  ASSERT_EQ(vrt->GetGeoTransform(gt_vrt), CE_None);
  for (int i = 0; i < 6; ++i) EXPECT_NEAR(gt_ours[i], gt_vrt[i], 1e-9) << i;
  ASSERT_NE(ours->GetSpatialRef(), nullptr);
  EXPECT_TRUE(ours->GetSpatialRef()->IsSame(vrt->GetSpatialRef()));
  ASSERT_EQ(ours->GetRasterCount(), 2);
  EXPECT_EQ(ours->GetRasterBand(1)->GetRasterDataType(), GDT_UInt16);
  EXPECT_EQ(ours->GetRasterBand(2)->GetColorInterpretation(), GCI_AlphaBand);
  EXPECT_EQ(ours->GetRasterBand(1)->GetMaskFlags(), GMF_ALPHA | GMF_PER_DATASET);
  const int overviews = vrt->GetRasterBand(1)->GetOverviewCount();
  ASSERT_GE(overviews, 1);
  ASSERT_EQ(ours->GetRasterBand(1)->GetOverviewCount(), overviews);
  GdalErrors errors;
  for (int b = 1; b <= 2; ++b) {
    const int sum = Checksum(ours->GetRasterBand(b));
    EXPECT_EQ(sum, Checksum(vrt->GetRasterBand(b))) << "band " << b;
    EXPECT_NE(sum, 0);
    for (int o = 0; o < overviews; ++o) {
      GDALRasterBand* a = ours->GetRasterBand(b)->GetOverview(o);
      GDALRasterBand* v = vrt->GetRasterBand(b)->GetOverview(o);
      ASSERT_EQ(a->GetXSize(), v->GetXSize());
      ASSERT_EQ(a->GetYSize(), v->GetYSize());
      EXPECT_EQ(Checksum(a), Checksum(v)) << "band " << b << " overview " << o;
    }
  }
  EXPECT_EQ(errors.count, 0) << errors.last;
  // A painted sample and an absent tile (top-right, tile (-1, 1)) read back exactly.
  uint16_t value = 0, alpha = 1;
  ASSERT_EQ(ours->GetRasterBand(1)->RasterIO(GF_Read, 256 - 100, 256 - 50, 1, 1, &value, 1, 1,
                                             GDT_UInt16, 0, 0, nullptr),
            CE_None);
  EXPECT_EQ(value, 1000);
  ASSERT_EQ(ours->GetRasterBand(2)->RasterIO(GF_Read, 700, 10, 1, 1, &alpha, 1, 1, GDT_UInt16, 0, 0,
                                             nullptr),
            CE_None);
  EXPECT_EQ(alpha, 0);
}

TEST_F(GdalDriverTest, OpensTheManifestPathAndTellsTheStoresMetadata) {
  auto ds = OpenWith(dir_ / "manifest.json", "IRMOSAIC");
  ASSERT_TRUE(ds);
  EXPECT_STREQ(ds->GetMetadataItem("IRMOSAIC_GENERATION"), "1");
  EXPECT_STREQ(ds->GetMetadataItem("IRMOSAIC_FRAME_COUNT"), "2");
  EXPECT_NEAR(std::atof(ds->GetMetadataItem("IRMOSAIC_TIME_MIN_S")), 10.0, 1e-6);
  EXPECT_NEAR(std::atof(ds->GetMetadataItem("IRMOSAIC_TIME_MAX_S")), 10.04, 1e-6);
  EXPECT_NEAR(std::atof(ds->GetMetadataItem("IRMOSAIC_GSD_M")), kGsd, 1e-12);
  EXPECT_NEAR(std::atof(ds->GetMetadataItem("IRMOSAIC_ORIGIN_LAT_DEG")), kLat0, 1e-9);
  EXPECT_NEAR(std::atof(ds->GetMetadataItem("IRMOSAIC_ORIGIN_LON_DEG")), kLon0, 1e-9);
  EXPECT_STREQ(ds->GetRasterBand(1)->GetDescription(), "mosaic");
}

TEST_F(GdalDriverTest, TheDriverUnderTestIsThisBuildsNotAnInstalledPlugIn) {
  RegisterInProcess();
  GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("IRMOSAIC");
  ASSERT_NE(driver, nullptr);
  Dl_info where;
  ASSERT_NE(::dladdr(reinterpret_cast<void*>(driver->pfnOpen), &where), 0);
  EXPECT_EQ(std::string(where.dli_fname).find("gdal_IRMOSAIC"), std::string::npos)
      << where.dli_fname;
}

TEST_F(GdalDriverTest, RefusesUpdateWithAClearMessage) {
  GdalErrors errors;
  auto ds = OpenWith(dir_, "IRMOSAIC", /*update=*/true);
  EXPECT_FALSE(ds);
  EXPECT_NE(errors.last.find("read-only"), std::string::npos) << errors.last;
}

TEST_F(GdalDriverTest, IdentifyIgnoresOtherFilesQuietly) {
  GdalErrors errors;
  RegisterInProcess();
  GDALOpenInfo tile((dir_ / "tiles/0/0_0.tif").c_str(), GA_ReadOnly);
  GDALOpenInfo parent(dir_.parent_path().c_str(), GA_ReadOnly);
  GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("IRMOSAIC");
  ASSERT_NE(driver, nullptr);
  EXPECT_FALSE(driver->pfnIdentify(&tile));
  EXPECT_FALSE(driver->pfnIdentify(&parent));
  GDALOpenInfo store(dir_.c_str(), GA_ReadOnly);
  EXPECT_TRUE(driver->pfnIdentify(&store));
  EXPECT_EQ(errors.count, 0);
}

TEST_F(GdalDriverTest, IdentifyKnowsNewAndOldManifestsButNotOtherJson) {
  GdalErrors errors;
  GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("IRMOSAIC");
  ASSERT_NE(driver, nullptr);
  const auto identified = [&](const fs::path& path) {
    GDALOpenInfo info(path.c_str(), GA_ReadOnly);
    return driver->pfnIdentify(&info) != 0;
  };
  // TileStore writes "format" first (so the first KiB tells) and whole-pixel bounds as integers.
  std::ifstream in(dir_ / "manifest.json");
  const std::string text((std::istreambuf_iterator<char>(in)), {});
  EXPECT_EQ(text.rfind("{\n \"format\": \"irmosaic-store\"", 0), 0u) << text.substr(0, 80);
  const nlohmann::json j = nlohmann::json::parse(text);
  EXPECT_TRUE(j["bounds_px"]["col_min"].is_number_integer());
  // Stores written before: keys sorted ("alpha_max" first, "format" beyond the first KiB after
  // the WKT and a long application state), bounds as reals. Still identified and opened.
  nlohmann::json old = j;
  old["application"] = {{"state", std::string(4000, 'x')}};
  for (const char* key : {"col_min", "row_min", "col_max", "row_max"}) {
    old["bounds_px"][key] = old["bounds_px"][key].get<double>();
  }
  const std::string old_text = old.dump(1);
  ASSERT_GT(old_text.find("\"format\""), 4000u);
  std::ofstream(dir_ / "manifest.json", std::ios::trunc) << old_text;
  EXPECT_TRUE(identified(dir_));
  EXPECT_TRUE(identified(dir_ / "manifest.json"));
  auto ds = OpenWith(dir_, "IRMOSAIC");
  ASSERT_TRUE(ds);
  EXPECT_EQ(ds->GetRasterXSize(), 3 * 256);
  // Other JSON named manifest.json (a web app's, a GeoJSON): not claimed, no message.
  const fs::path other = dir_.parent_path() / "webapp";
  fs::create_directories(other);
  std::ofstream(other / "manifest.json") << "{\"name\": \"app\", \"icons\": []}";
  EXPECT_FALSE(identified(other));
  EXPECT_FALSE(identified(other / "manifest.json"));
  EXPECT_EQ(errors.count, 0) << errors.last;
}

TEST_F(GdalDriverTest, ReopenAfterAPublishShowsTheLargerExtentAndTheNewGeneration) {
  auto before = OpenWith(dir_, "IRMOSAIC");
  ASSERT_TRUE(before);
  const int width = before->GetRasterXSize(), height = before->GetRasterYSize();
  PaintSquare(store_.get(), {800, -700}, 100, 3000);  // East (tile col 3) and north (row -3).
  store_->PutFrameRecord(Frame(2, 10.08));
  store_->WaitPublished(store_->RequestPublish());
  auto after = OpenWith(dir_, "IRMOSAIC");
  ASSERT_TRUE(after);
  EXPECT_EQ(after->GetRasterXSize(), width + 512);   // Cols -1..3.
  EXPECT_EQ(after->GetRasterYSize(), height + 512);  // Rows -3..1.
  EXPECT_STREQ(after->GetMetadataItem("IRMOSAIC_GENERATION"), "2");
  EXPECT_STREQ(after->GetMetadataItem("IRMOSAIC_FRAME_COUNT"), "3");
  uint16_t value = 0;
  // Mosaic pixel (800, -700) is at dataset (800 + 256, -700 + 768).
  ASSERT_EQ(after->GetRasterBand(1)->RasterIO(GF_Read, 1056, 68, 1, 1, &value, 1, 1, GDT_UInt16, 0,
                                              0, nullptr),
            CE_None);
  EXPECT_EQ(value, 3000);
  // The dataset opened before keeps reading its own extent without error.
  GdalErrors errors;
  EXPECT_NE(Checksum(before->GetRasterBand(1)), 0);
  EXPECT_EQ(errors.count, 0) << errors.last;
}

// Reads one sample of `band` (dataset pixel x, y) as a double; NaN on a read error.
double Sample(GDALRasterBand* band, int x, int y) {
  double value = 0.0;
  if (band->RasterIO(GF_Read, x, y, 1, 1, &value, 1, 1, GDT_Float64, 0, 0, nullptr) != CE_None) {
    return std::nan("");
  }
  return value;
}

GDALDatasetUniquePtr OpenWithOptions(const fs::path& path, const char* option) {
  RegisterInProcess();
  const char* const allowed[] = {"IRMOSAIC", nullptr};
  const char* const options[] = {option, nullptr};
  return GDALDatasetUniquePtr(GDALDataset::Open(path.c_str(), GDAL_OF_RASTER | GDAL_OF_READONLY,
                                                allowed, options, nullptr));
}

// A client that keeps the dataset open (QGIS does, for the layer's life) sees tiles published
// after its open inside its extent, at level 0 and in the overviews, even where it had read (and
// GDAL had cached) the empty block before; with LIVE=NO it keeps the state of its open.
TEST_F(GdalDriverTest, AnOpenDatasetShowsTilesPublishedLaterInsideItsExtent) {
  auto live = OpenWith(dir_, "IRMOSAIC");
  auto fixed = OpenWithOptions(dir_, "LIVE=NO");
  ASSERT_TRUE(live && fixed);
  ASSERT_EQ(live->GetRasterXSize(), 768);  // Tiles -1..1 of 256 pixels.
  EXPECT_STREQ(live->GetMetadataItem("IRMOSAIC_LIVE"), "YES");
  EXPECT_STREQ(fixed->GetMetadataItem("IRMOSAIC_LIVE"), "NO");
  // Tile (row -1, col 1) is absent: mosaic pixel (310, -190) is dataset pixel (566, 66).
  for (GDALDataset* ds : {live.get(), fixed.get()}) {
    std::vector<uint16_t> block(256 * 256);  // The whole block, so GDAL caches it.
    ASSERT_EQ(ds->GetRasterBand(1)->RasterIO(GF_Read, 512, 0, 256, 256, block.data(), 256, 256,
                                             GDT_UInt16, 0, 0, nullptr),
              CE_None);
    EXPECT_EQ(Sample(ds->GetRasterBand(1), 566, 66), 0.0);
    EXPECT_EQ(Sample(ds->GetRasterBand(2), 566, 66), 0.0);
    EXPECT_EQ(Sample(ds->GetRasterBand(2)->GetOverview(0), 283, 33), 0.0);
  }
  PaintSquare(store_.get(), {300, -200}, 50, 4000);
  store_->PutFrameRecord(Frame(2, 10.08));
  store_->WaitPublished(store_->RequestPublish());
  GdalErrors errors;
  // Row 10 of the square: 4000 plus the gradient's 10.
  EXPECT_EQ(Sample(live->GetRasterBand(1), 566, 66), 4010.0);
  EXPECT_EQ(Sample(live->GetRasterBand(2), 566, 66), 65535.0);  // UInt16 store: alpha 65535.
  EXPECT_GT(Sample(live->GetRasterBand(1)->GetOverview(0), 283, 33), 3900.0);
  EXPECT_GT(Sample(live->GetRasterBand(2)->GetOverview(0), 283, 33), 0.0);
  EXPECT_STREQ(live->GetMetadataItem("IRMOSAIC_GENERATION"), "2");
  EXPECT_STREQ(live->GetMetadataItem("IRMOSAIC_FRAME_COUNT"), "3");
  EXPECT_EQ(live->GetRasterXSize(), 768);  // The extent stays the one opened.
  EXPECT_EQ(Sample(fixed->GetRasterBand(1), 566, 66), 0.0);
  EXPECT_EQ(Sample(fixed->GetRasterBand(2), 566, 66), 0.0);
  EXPECT_STREQ(fixed->GetMetadataItem("IRMOSAIC_GENERATION"), "1");
  EXPECT_EQ(errors.count, 0) << errors.last;
}

// A live dataset held open while another process publishes (as QGIS holds a layer during a
// flight): every read succeeds, every covered tile is whole and no older than the generation the
// read took, and the reader follows the writer through its generations. Generation g paints a
// growing square of 128-pixel tiles with 1000 + g, inside the planned extent set at the start.
TEST(GdalDriverLiveTest, AHeldDatasetFollowsAWriterProcessWithoutErrorsOrTornTiles) {
  const fs::path dir = FreshDir("live_writer") / "s.irmosaic";
  constexpr int kTile = 128, kGenerations = 30;
  const pid_t writer = fork();
  if (writer == 0) {
    int code = 0;
    try {
      TileStoreOptions options;
      options.path = dir.string();
      options.tile_size = kTile;
      const LocalFrame frame(kLat0, kLon0);
      auto store = TileStore::Open(options, {kLat0, kLon0, kGsd, frame.CrsWkt()});
      store->SetPlannedBoundsPx(cv::Rect(-kTile, -kTile, 7 * kTile, 7 * kTile));
      for (int64_t g = 1; g <= kGenerations; ++g) {
        const int tiles = 2 + static_cast<int>(std::min<int64_t>(g / 3, 5));
        cv::Mat image(tiles * kTile, tiles * kTile, CV_16U, cv::Scalar(1000.0 + g));
        store->Paint(image, cv::Mat(image.size(), CV_32F, cv::Scalar(1.0f)), {-kTile, -kTile});
        store->PutFrameRecord(Frame(g, 0.04 * static_cast<double>(g)));
        store->WaitPublished(store->RequestPublish());
        usleep(20000);  // A flight publishes a few times a second.
      }
      store->Close();
    } catch (...) {
      code = 1;
    }
    _exit(code);
  }
  // A guard against a hang, not a speed bound: under ASan on a loaded 2-core machine the 30
  // generations took over 60 s (CI of 5a94093, with benchmarks beside it).
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(300);
  while (!fs::exists(dir / "manifest.json") && std::chrono::steady_clock::now() < deadline) {
    usleep(2000);
  }
  GDALDatasetUniquePtr ds;
  while (!ds && std::chrono::steady_clock::now() < deadline) {  // Until the first tiles.
    GdalErrors quiet;
    ds = OpenWith(dir, "IRMOSAIC");
    if (!ds) usleep(2000);
  }
  ASSERT_TRUE(ds) << "no generation with tiles within 300 s";
  ASSERT_EQ(ds->GetRasterXSize(), 7 * kTile);  // The planned extent from the first open.
  int reads = 0, problems = 0, status = 0;
  std::set<int64_t> generations;
  std::string first_problem;
  GdalErrors errors;
  const int n = 7 * kTile;
  cv::Mat data(n, n, CV_16U), alpha(n, n, CV_16U);
  bool writing = true;
  while (writing && std::chrono::steady_clock::now() < deadline) {
    writing = waitpid(writer, &status, WNOHANG) == 0;
    std::string problem;
    if (ds->GetRasterBand(1)->RasterIO(GF_Read, 0, 0, n, n, data.data, n, n, GDT_UInt16, 0, 0,
                                       nullptr) != CE_None ||
        ds->GetRasterBand(2)->RasterIO(GF_Read, 0, 0, n, n, alpha.data, n, n, GDT_UInt16, 0, 0,
                                       nullptr) != CE_None) {
      problem = "read failed: " + errors.last;
    }
    const int64_t generation = std::atoll(ds->GetMetadataItem("IRMOSAIC_GENERATION"));
    generations.insert(generation);
    for (int y = 0; y < n && problem.empty(); y += kTile) {
      for (int x = 0; x < n && problem.empty(); x += kTile) {
        const cv::Rect tile(x, y, kTile, kTile);
        double lo = 0, hi = 0;
        cv::minMaxLoc(data(tile), &lo, &hi);
        if (hi == 0) continue;  // Not painted (yet, for this read).
        if (lo != hi) problem = "torn tile: " + std::to_string(lo) + ".." + std::to_string(hi);
        if (lo < 1000.0 + static_cast<double>(generation)) {
          problem =
              "tile " + std::to_string(lo) + " older than generation " + std::to_string(generation);
        }
        cv::minMaxLoc(alpha(tile), &lo, &hi);
        if (lo != 65535) problem = "painted tile not wholly covered in the alpha band";
      }
    }
    ++reads;
    if (!problem.empty() && problems++ == 0) first_problem = problem;
  }
  if (writing) {  // The deadline passed: stop the writer before its folder is removed.
    kill(writer, SIGKILL);
    waitpid(writer, &status, 0);
    FAIL() << "the writer had not finished its " << kGenerations << " generations in 300 s";
  }
  ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << "writer failed";
  EXPECT_EQ(problems, 0) << first_problem << " (" << reads << " reads)";
  EXPECT_EQ(errors.count, 0) << errors.last;
  EXPECT_GE(reads, 5);
  // It followed the writer: through several generations to the last (the loop reads once more
  // after the writer exited); held with LIVE=NO it stays at the generation of its open.
  EXPECT_GE(generations.size(), 3u) << reads << " reads";
  EXPECT_EQ(*generations.rbegin(), kGenerations);
  fs::remove_all(dir.parent_path());
}

// A planned extent (the flight's, foreseen from POS) is the extent served from the first
// generation; tiles painted later inside it show through a dataset opened before them.
TEST_F(GdalDriverTest, ThePlannedExtentIsServedAndFillsInWithoutAReopen) {
  store_->SetPlannedBoundsPx(cv::Rect(-600, -600, 2100, 1500));  // Cols -600..1500, rows ..900.
  store_->WaitPublished(store_->RequestPublish());
  {
    std::ifstream in(dir_ / "manifest.json");
    const nlohmann::json manifest = nlohmann::json::parse(in);
    EXPECT_EQ(manifest["planned_bounds_px"]["col_min"], -600);
    EXPECT_EQ(manifest["planned_bounds_px"]["row_max"], 900);
  }
  auto ds = OpenWith(dir_, "IRMOSAIC");
  ASSERT_TRUE(ds);
  // Tiles -3..5 across (floor(-600/256) = -3, ceil(1500/256) = 6), -3..3 down.
  EXPECT_EQ(ds->GetRasterXSize(), 9 * 256);
  EXPECT_EQ(ds->GetRasterYSize(), 7 * 256);
  double gt[6];
  ASSERT_EQ(ds->GetGeoTransform(gt), CE_None);
  EXPECT_DOUBLE_EQ(gt[0], (-3 * 256 - 0.5) * kGsd);
  EXPECT_DOUBLE_EQ(gt[3], (3 * 256 + 0.5) * kGsd);
  // Mosaic pixel (1300, 700), beyond the painted tiles: dataset pixel (1300 + 768, 700 + 768).
  EXPECT_EQ(Sample(ds->GetRasterBand(2), 2068, 1468), 0.0);
  PaintSquare(store_.get(), {1290, 690}, 40, 5000);
  store_->WaitPublished(store_->RequestPublish());
  EXPECT_EQ(Sample(ds->GetRasterBand(1), 2068, 1468), 5010.0);
  EXPECT_EQ(Sample(ds->GetRasterBand(2), 2068, 1468), 65535.0);
  // The plan survives a resume.
  store_->Close();
  store_.reset();
  TileStoreOptions options;
  options.path = dir_.string();
  options.tile_size = 256;
  options.mode = TileStoreOptions::Mode::kResume;
  const LocalFrame frame(kLat0, kLon0);
  store_ = TileStore::Open(options, {kLat0, kLon0, kGsd, frame.CrsWkt()});
  PaintSquare(store_.get(), {0, 0}, 10, 100);
  store_->WaitPublished(store_->RequestPublish());
  auto reopened = OpenWith(dir_, "IRMOSAIC");
  ASSERT_TRUE(reopened);
  EXPECT_EQ(reopened->GetRasterXSize(), 9 * 256);
}

TEST_F(GdalDriverTest, FootprintsAreAVectorLayerBesideTheRaster) {
  // Vector-only (as ogrinfo asks): the frames layer of frames.gpkg, no bands.
  auto vector = OpenKinds(dir_, GDAL_OF_VECTOR);
  ASSERT_TRUE(vector);
  EXPECT_EQ(vector->GetRasterCount(), 0);
  ASSERT_EQ(vector->GetLayerCount(), 1);
  OGRLayer* layer = vector->GetLayer(0);
  ASSERT_NE(layer, nullptr);
  EXPECT_STREQ(layer->GetName(), "frames");
  EXPECT_EQ(layer->GetFeatureCount(), 2);
  EXPECT_EQ(wkbFlatten(layer->GetGeomType()), wkbPolygon);
  // Frame 1: 10.04 s, its 10 m x 10 m footprint in the mosaic plane (metres).
  OGRFeatureUniquePtr feature(layer->GetFeature(2));  // FID = frame index + 1.
  ASSERT_TRUE(feature);
  EXPECT_EQ(feature->GetFieldAsInteger64("frame_index"), 1);
  EXPECT_NEAR(feature->GetFieldAsDouble("time_s"), 10.04, 1e-9);
  OGREnvelope envelope;
  feature->GetGeometryRef()->getEnvelope(&envelope);
  EXPECT_NEAR(envelope.MaxX - envelope.MinX, 10.0, 1e-9);
  EXPECT_NEAR(envelope.MaxY - envelope.MinY, 10.0, 1e-9);
  // The layer's CRS is the raster's.
  auto both = OpenKinds(dir_, GDAL_OF_RASTER | GDAL_OF_VECTOR);
  ASSERT_TRUE(both);
  EXPECT_EQ(both->GetRasterCount(), 2);
  ASSERT_EQ(both->GetLayerCount(), 1);
  ASSERT_NE(both->GetLayer(0)->GetSpatialRef(), nullptr);
  EXPECT_TRUE(both->GetLayer(0)->GetSpatialRef()->IsSame(both->GetSpatialRef()));
  // Raster-only (gdalinfo, QGIS raster layers): frames.gpkg is not even opened.
  auto raster = OpenKinds(dir_, GDAL_OF_RASTER);
  ASSERT_TRUE(raster);
  EXPECT_EQ(raster->GetLayerCount(), 0);
  // The layer follows the store: a reopen after a publish counts the new frame.
  store_->PutFrameRecord(Frame(2, 10.08));
  store_->WaitPublished(store_->RequestPublish());
  auto reopened = OpenKinds(dir_, GDAL_OF_VECTOR);
  ASSERT_TRUE(reopened);
  EXPECT_EQ(reopened->GetLayer(0)->GetFeatureCount(), 3);
}

TEST(GdalDriverEmptyStoreTest, AStoreWithNoTilesYetHasItsLayerButNoRaster) {
  const fs::path dir = FreshDir("empty") / "s.irmosaic";
  TileStoreOptions options;
  options.path = dir.string();
  options.tile_size = 256;
  const LocalFrame frame(kLat0, kLon0);
  auto store = TileStore::Open(options, {kLat0, kLon0, kGsd, frame.CrsWkt()});
  store->PutFrameRecord(Frame(0, 1.0));
  store->WaitPublished(store->RequestPublish());
  {
    GdalErrors errors;
    EXPECT_FALSE(OpenKinds(dir, GDAL_OF_RASTER));
    EXPECT_NE(errors.last.find("no tiles yet"), std::string::npos) << errors.last;
    auto vector = OpenKinds(dir, GDAL_OF_VECTOR);
    ASSERT_TRUE(vector);
    EXPECT_EQ(vector->GetRasterCount(), 0);
    ASSERT_EQ(vector->GetLayerCount(), 1);
    EXPECT_EQ(vector->GetLayer(0)->GetFeatureCount(), 1);
  }
  store->Close();
  fs::remove_all(dir.parent_path());
}

// Malformed manifests: each is refused with a message, never a crash or a read outside.
class MalformedManifestTest : public GdalDriverTest {
 protected:
  void SetUp() override {
    GdalDriverTest::SetUp();
    std::ifstream in(dir_ / "manifest.json");
    original_ = nlohmann::json::parse(in);
  }
  // The manifest as published (each case edits a fresh copy).
  nlohmann::json Manifest() const { return original_; }
  nlohmann::json original_;
  void Write(const std::string& text) {
    std::ofstream out(dir_ / "manifest.json", std::ios::trunc);
    out << text;
  }
  // Opens through the driver; returns the error message (empty if it opened).
  std::string Refusal() {
    GdalErrors errors;
    auto ds = OpenWith(dir_, "IRMOSAIC");
    if (ds) return "";
    return errors.last.empty() ? "(not recognised)" : errors.last;
  }
};

TEST_F(MalformedManifestTest, Truncated) {
  std::ifstream in(dir_ / "manifest.json");
  const std::string text((std::istreambuf_iterator<char>(in)), {});
  for (size_t cut : {size_t{0}, size_t{1}, text.size() / 3, text.size() / 2, text.size() - 3}) {
    Write(text.substr(0, cut));
    const std::string message = Refusal();
    EXPECT_NE(message, "") << "cut at " << cut;
    if (cut > 0) {
      EXPECT_NE(message.find("IRMOSAIC"), std::string::npos) << message;
    }
  }
}

TEST_F(MalformedManifestTest, WrongTypes) {
  for (const char* key : {"tile_size", "gsd_m", "levels", "crs_wkt", "generation", "data_type"}) {
    nlohmann::json j = Manifest();
    j[key] = nlohmann::json::object({{"x", 1}});
    Write(j.dump());
    EXPECT_NE(Refusal().find(key), std::string::npos) << key;
  }
  nlohmann::json j = manifest_json::AsFormat1(Manifest());
  j["levels"][0]["tiles"][0] = "0_0";
  Write(j.dump());
  EXPECT_NE(Refusal().find("[row, col]"), std::string::npos);
  j = Manifest();
  j["tile_size"] = 256.5;
  Write(j.dump());
  EXPECT_NE(Refusal().find("tile_size"), std::string::npos);
}

TEST_F(MalformedManifestTest, AbsurdSizesAndCounts) {
  const auto refused_for = [&](const std::function<void(nlohmann::json&)>& edit) {
    nlohmann::json j = Manifest();
    edit(j);
    Write(j.dump());
    return Refusal();
  };
  EXPECT_NE(refused_for([](auto& j) { j["tile_size"] = 1 << 30; }), "");
  EXPECT_NE(refused_for([](auto& j) { j["tile_size"] = -256; }), "");
  EXPECT_NE(refused_for([](auto& j) { j["gsd_m"] = -0.5; }), "");
  EXPECT_NE(refused_for([](auto& j) { j["format_version"] = 3; }).find("newer"), std::string::npos);
  EXPECT_NE(refused_for([](auto& j) {
              j = manifest_json::AsFormat1(j);
              j["levels"][0]["tiles"].push_back({0, 1000000000000LL});
            }),
            "");
  EXPECT_NE(refused_for([](auto& j) {
              j = manifest_json::AsFormat1(j);
              j["levels"][0]["tiles"].push_back({0, 18446744073709551615ULL});
            }),
            "");
  EXPECT_NE(refused_for([](auto& j) {
              j = manifest_json::AsFormat1(j);
              j["levels"][0]["tiles"].push_back({INT64_MIN, 0});
            }),
            "");
  // Tiles of 8192 two million tiles apart: a raster beyond GDAL's int size (both formats).
  EXPECT_NE(refused_for([](auto& j) {
              j = manifest_json::AsFormat1(j);
              j["tile_size"] = 8192;
              j["levels"][0]["tiles"].push_back({0, 1000000});
              j["levels"][0]["tiles"].push_back({0, -1000000});
              j["bounds_px"] = nullptr;
            }).find("beyond"),
            std::string::npos);
  EXPECT_NE(refused_for([](auto& j) {
              j["tile_size"] = 8192;
              const std::string one = "8" + std::string(63, '0');
              j["levels"][0]["blocks"].push_back({0, 62500, one});  // Tile (0, 1000000).
              j["levels"][0]["blocks"].push_back({0, -62500, one});
              j["bounds_px"] = nullptr;
            }).find("beyond"),
            std::string::npos);
  EXPECT_NE(refused_for([](auto& j) {
              for (int l = 0; l < 100; ++l) j["levels"].push_back(j["levels"][0]);
            }),
            "");
  EXPECT_NE(refused_for([](auto& j) { j["levels"] = nlohmann::json::array(); }), "");
  EXPECT_NE(refused_for([](auto& j) { j["bounds_px"]["col_max"] = 1 << 30; }).find("bounds_px"),
            std::string::npos);
  // Deep nesting is refused before parsing.
  Write("{\"format\": \"irmosaic-store\", \"a\": " + std::string(100000, '[') +
        std::string(100000, ']') + "}");
  EXPECT_NE(Refusal().find("nests"), std::string::npos);
}

TEST_F(MalformedManifestTest, PlannedBoundsThatAreEmptyOrHuge) {
  const auto refused_for = [&](const nlohmann::json& planned) {
    nlohmann::json j = Manifest();
    j["planned_bounds_px"] = planned;
    Write(j.dump());
    return Refusal();
  };
  EXPECT_NE(refused_for({{"col_min", 10}, {"row_min", 0}, {"col_max", 10}, {"row_max", 5}})
                .find("planned_bounds_px"),
            std::string::npos);
  EXPECT_NE(refused_for({{"col_min", -1e12}, {"row_min", 0}, {"col_max", 10}, {"row_max", 5}})
                .find("planned_bounds_px: field \"col_min\""),
            std::string::npos);
  EXPECT_NE(refused_for({{"col_min", 0}, {"row_min", 0}, {"col_max", "far"}, {"row_max", 5}})
                .find("planned_bounds_px: field \"col_max\""),
            std::string::npos);
  EXPECT_NE(refused_for("wide").find("planned_bounds_px"), std::string::npos);
  EXPECT_EQ(refused_for(nullptr), "");  // Absent: the painted extent.
}

// Format 2's block lists damaged or edited: each refused with a message naming the field.
TEST_F(MalformedManifestTest, DamagedBlockListIsRefusedNamingTheField) {
  const std::string bits = Manifest()["levels"][0]["blocks"][0][2];
  const std::string appended =  // The index a block pushed onto level 0's list gets.
      "levels[0].blocks[" + std::to_string(Manifest()["levels"][0]["blocks"].size()) + "]";
  auto block = [](nlohmann::json& j) -> nlohmann::json& { return j["levels"][0]["blocks"][0]; };
  const std::vector<std::tuple<std::string, std::string, std::function<void(nlohmann::json&)>>>
      cases = {
          {"63 digits", "levels[0].blocks[0]", [&](auto& j) { block(j)[2] = bits.substr(1); }},
          {"65 digits", "levels[0].blocks[0]", [&](auto& j) { block(j)[2] = bits + "0"; }},
          {"upper case", "levels[0].blocks[0]",
           [&](auto& j) { block(j)[2] = "F" + bits.substr(1); }},
          {"not hex", "levels[0].blocks[0]", [&](auto& j) { block(j)[2] = "-" + bits.substr(1); }},
          {"bitmap a number", "levels[0].blocks[0]", [&](auto& j) { block(j)[2] = 7; }},
          {"no tile", "levels[0].blocks[0]", [&](auto& j) { block(j)[2] = std::string(64, '0'); }},
          {"two values", "levels[0].blocks[0]", [&](auto& j) { block(j).erase(2); }},
          {"index a real", "levels[0].blocks[0]", [&](auto& j) { block(j)[0] = 0.0; }},
          {"listed twice", appended,
           [&](auto& j) { j["levels"][0]["blocks"].push_back(block(j)); }},
          {"block row 2^62", "levels[0].blocks[0]",
           [&](auto& j) { block(j)[0] = int64_t{1} << 62; }},
          {"block col 2^16", "levels[0].blocks[0]", [&](auto& j) { block(j)[1] = 1 << 16; }},
          {"block col -2^16 - 1", "levels[0].blocks[0]",
           [&](auto& j) { block(j)[1] = -(1 << 16) - 1; }},
          {"block row 2^64 - 1", "levels[0].blocks[0]",
           [&](auto& j) { block(j)[0] = 18446744073709551615ULL; }},
          {"block row INT64_MIN", "levels[0].blocks[0]", [&](auto& j) { block(j)[0] = INT64_MIN; }},
          {"tiles and blocks", "levels[0]",
           [&](auto& j) {
             j["levels"][0]["tiles"] = nlohmann::json::array({{0, 0}});
           }},
          {"blocks missing", "levels[0].blocks", [&](auto& j) { j["levels"][0].erase("blocks"); }},
          {"blocks an object", "levels[0].blocks",
           [&](auto& j) {
             j["levels"][0]["blocks"] = {{"0", "1"}};
           }},
          {"format 1 holding blocks", "levels[0].tiles", [](auto& j) { j["format_version"] = 1; }},
          {"overview level damaged", "levels[1].blocks[0]",
           [](auto& j) { j["levels"][1]["blocks"][0][2] = "x"; }},
      };
  for (const auto& [name, field, edit] : cases) {
    nlohmann::json j = Manifest();
    edit(j);
    Write(j.dump());
    const std::string message = Refusal();
    EXPECT_NE(message.find(field), std::string::npos) << name << ": " << message;
  }
  // More tiles than the driver takes, through blocks of 256 (the cap counts tiles, not entries).
  nlohmann::json j = Manifest();
  j["bounds_px"] = nullptr;
  nlohmann::json& blocks = j["levels"][0]["blocks"];
  for (int64_t k = 1; k <= 33000; ++k) blocks.push_back({k / 181, k % 181, std::string(64, 'f')});
  Write(j.dump());
  EXPECT_NE(Refusal().find("more than"), std::string::npos);
}

// A store written before format 2 (tiles listed one by one) opens with the same raster.
TEST_F(MalformedManifestTest, FormatOneManifestOpensWithTheSameTiles) {
  std::string geotransform;
  auto read = [&](const char* version) {
    auto ds = OpenWith(dir_, "IRMOSAIC");
    if (!ds) return std::vector<int>{};
    EXPECT_STREQ(ds->GetMetadataItem("IRMOSAIC_FORMAT_VERSION"), version);
    double gt[6];
    ds->GetGeoTransform(gt);
    geotransform = std::to_string(gt[0]) + "," + std::to_string(gt[3]) + "," +
                   std::to_string(ds->GetRasterXSize()) + "," +
                   std::to_string(ds->GetRasterYSize());
    std::vector<int> sums;
    for (int b = 1; b <= 2; ++b) {
      GDALRasterBand* band = ds->GetRasterBand(b);
      sums.push_back(Checksum(band));
      for (int o = 0; o < band->GetOverviewCount(); ++o) {
        sums.push_back(Checksum(band->GetOverview(o)));
      }
    }
    return sums;
  };
  const std::vector<int> v2 = read("2");
  const std::string v2_geotransform = geotransform;
  ASSERT_GE(v2.size(), 4u);  // Two bands, at least one overview each.
  const nlohmann::json v1 = manifest_json::AsFormat1(Manifest());
  ASSERT_EQ(manifest_json::LevelTiles(v1["levels"][0]).size(), 5u);  // The L of MakeStore.
  Write(v1.dump(1));
  EXPECT_EQ(Refusal(), "");
  EXPECT_EQ(read("1"), v2);
  EXPECT_EQ(geotransform, v2_geotransform);
}

TEST_F(MalformedManifestTest, PathsAndLevelsOutsideTheStore) {
  nlohmann::json j = Manifest();
  j["levels"][0]["path_pattern"] = "../../etc/passwd";
  Write(j.dump());
  EXPECT_NE(Refusal().find("path_pattern"), std::string::npos);
  j = Manifest();
  j["levels"][0]["level"] = -1;
  Write(j.dump());
  EXPECT_NE(Refusal().find("level"), std::string::npos);
  j = Manifest();
  j["levels"][1]["level"] = 7;
  Write(j.dump());
  EXPECT_NE(Refusal(), "");
}

TEST_F(MalformedManifestTest, SymlinkedTileOutOfTheStoreIsNotRead) {
  // A valid GeoTIFF outside the store, linked in place of a tile: opening works, reading the
  // tile fails with a message and returns no byte of it.
  const fs::path outside = dir_.parent_path() / "outside.tif";
  fs::copy_file(dir_ / "tiles/0/0_0.tif", outside);
  fs::remove(dir_ / "tiles/0/0_0.tif");
  fs::create_symlink(outside, dir_ / "tiles/0/0_0.tif");
  auto ds = OpenWith(dir_, "IRMOSAIC");
  ASSERT_TRUE(ds);
  GdalErrors errors;
  uint16_t value = 0;
  EXPECT_EQ(ds->GetRasterBand(1)->RasterIO(GF_Read, 256, 256, 1, 1, &value, 1, 1, GDT_UInt16, 0, 0,
                                           nullptr),
            CE_Failure);
  EXPECT_NE(errors.last.find("outside the store"), std::string::npos) << errors.last;
  EXPECT_EQ(value, 0);
  // The store folder itself behind a symlink is fine: containment is checked after resolving.
  const fs::path link = dir_.parent_path() / "link.irmosaic";
  fs::remove(dir_ / "tiles/0/0_0.tif");
  fs::copy_file(outside, dir_ / "tiles/0/0_0.tif");
  fs::create_directory_symlink(dir_, link);
  auto via_link = OpenWith(link, "IRMOSAIC");
  ASSERT_TRUE(via_link);
  EXPECT_NE(Checksum(via_link->GetRasterBand(1)), 0);
}

TEST_F(MalformedManifestTest, FramesGpkgOutOfTheStoreIsNotOpened) {
  // frames.gpkg replaced by a symlink to a GeoPackage elsewhere: no layer from it; the raster
  // still opens when it was asked for too, a vector-only open is refused with the reason.
  const fs::path outside = dir_.parent_path() / "outside.gpkg";
  fs::copy_file(dir_ / "frames.gpkg", outside);
  fs::remove(dir_ / "frames.gpkg");
  fs::create_symlink(outside, dir_ / "frames.gpkg");
  GdalErrors errors;
  EXPECT_FALSE(OpenKinds(dir_, GDAL_OF_VECTOR));
  EXPECT_NE(errors.last.find("outside the store"), std::string::npos) << errors.last;
  auto both = OpenKinds(dir_, GDAL_OF_RASTER | GDAL_OF_VECTOR);
  ASSERT_TRUE(both);
  EXPECT_EQ(both->GetRasterCount(), 2);
  EXPECT_EQ(both->GetLayerCount(), 0);
  // Not a GeoPackage at all: refused likewise, never handed to another driver.
  fs::remove(dir_ / "frames.gpkg");
  std::ofstream(dir_ / "frames.gpkg") << "{\"type\": \"FeatureCollection\", \"features\": []}";
  EXPECT_FALSE(OpenKinds(dir_, GDAL_OF_VECTOR));
  EXPECT_NE(errors.last.find("not a GeoPackage"), std::string::npos) << errors.last;
}

TEST_F(MalformedManifestTest, FuzzEntryPointsRefuseWithoutThrowing) {
  EXPECT_EQ(IrmosaicDriverOpenForFuzzing(dir_.c_str()), 0);
  EXPECT_EQ(IrmosaicDriverOpenForFuzzing((dir_ / "nothing").c_str()), -1);
  const std::string bad = "{\"format\": \"irmosaic-store\", \"levels\": [[[";
  EXPECT_EQ(IrmosaicParseManifestForFuzzing(bad.data(), bad.size()), -1);
  std::ifstream in(dir_ / "manifest.json");
  const std::string good((std::istreambuf_iterator<char>(in)), {});
  EXPECT_EQ(IrmosaicParseManifestForFuzzing(good.data(), good.size()), 0);
}

// Real clients: GDAL's own programs load gdal_IRMOSAIC.so through GDAL_DRIVER_PATH.
std::string RunTool(const std::string& command, int* status) {
  const std::string full = "GDAL_DRIVER_PATH='" IRMOSAIC_GDAL_PLUGIN_DIR "' " + command + " 2>&1";
  FILE* pipe = ::popen(full.c_str(), "r");
  std::string out;
  if (pipe == nullptr) return out;
  char buffer[4096];
  size_t got = 0;
  while ((got = std::fread(buffer, 1, sizeof(buffer), pipe)) > 0) out.append(buffer, got);
  *status = ::pclose(pipe);
  return out;
}

TEST_F(GdalDriverTest, GdalToolsLoadThePlugInAndAgreeWithMosaicVrt) {
  int status = -1;
  const std::string formats = RunTool("gdalinfo --formats", &status);
  ASSERT_EQ(status, 0) << formats;
  EXPECT_NE(formats.find("IRMOSAIC -raster,vector- (ro"), std::string::npos) << formats;

  const std::string ours_text =
      RunTool("gdalinfo -json -checksum '" + dir_.string() + "'", &status);
  ASSERT_EQ(status, 0) << ours_text;
  const std::string vrt_text =
      RunTool("gdalinfo -json -checksum '" + (dir_ / "mosaic.vrt").string() + "'", &status);
  ASSERT_EQ(status, 0) << vrt_text;
  const nlohmann::json ours = nlohmann::json::parse(ours_text, nullptr, false);
  const nlohmann::json vrt = nlohmann::json::parse(vrt_text, nullptr, false);
  ASSERT_FALSE(ours.is_discarded()) << ours_text;
  ASSERT_FALSE(vrt.is_discarded()) << vrt_text;
  EXPECT_EQ(ours["driverShortName"], "IRMOSAIC");
  EXPECT_EQ(ours["size"], vrt["size"]);
  EXPECT_EQ(ours["size"][0], 768);
  for (int i = 0; i < 6; ++i) {
    EXPECT_NEAR(ours["geoTransform"][i].get<double>(), vrt["geoTransform"][i].get<double>(), 1e-9);
  }
  EXPECT_EQ(ours["coordinateSystem"]["wkt"], vrt["coordinateSystem"]["wkt"]);
  for (int b = 0; b < 2; ++b) {
    EXPECT_EQ(ours["bands"][b]["checksum"], vrt["bands"][b]["checksum"]) << b;
    EXPECT_EQ(ours["bands"][b]["overviews"], vrt["bands"][b]["overviews"]) << b;  // With sums.
  }
  EXPECT_GE(ours["bands"][0]["overviews"].size(), 1u);
  EXPECT_EQ(ours["metadata"][""]["IRMOSAIC_GENERATION"], "1");

  const fs::path tif = dir_.parent_path() / "copy.tif";
  const std::string translate = RunTool(
      "gdal_translate -q -of GTiff '" + dir_.string() + "' '" + tif.string() + "'", &status);
  ASSERT_EQ(status, 0) << translate;
  auto copy = OpenWith(tif, "GTiff");
  auto vrt_ds = OpenWith(dir_ / "mosaic.vrt", "VRT");
  ASSERT_TRUE(copy);
  ASSERT_TRUE(vrt_ds);
  EXPECT_EQ(Checksum(copy->GetRasterBand(1)), Checksum(vrt_ds->GetRasterBand(1)));
  EXPECT_EQ(copy->GetRasterBand(2)->GetColorInterpretation(), GCI_AlphaBand);
}

TEST_F(GdalDriverTest, OgrinfoListsTheFootprintsLayerWithItsFeatureCount) {
  int status = -1;
  const std::string listing = RunTool("ogrinfo -ro '" + dir_.string() + "'", &status);
  ASSERT_EQ(status, 0) << listing;
  EXPECT_NE(listing.find("using driver `IRMOSAIC'"), std::string::npos) << listing;
  EXPECT_NE(listing.find("1: frames (Polygon)"), std::string::npos) << listing;
  const std::string summary = RunTool("ogrinfo -ro -so '" + dir_.string() + "' frames", &status);
  ASSERT_EQ(status, 0) << summary;
  EXPECT_NE(summary.find("Feature Count: 2"), std::string::npos) << summary;
  // ogr2ogr copies it like any layer.
  const fs::path copy = dir_.parent_path() / "footprints.geojson";
  const std::string out =
      RunTool("ogr2ogr -f GeoJSON '" + copy.string() + "' '" + dir_.string() + "' frames", &status);
  ASSERT_EQ(status, 0) << out;
  GDALDatasetUniquePtr geojson(GDALDataset::Open(copy.c_str(), GDAL_OF_VECTOR));
  ASSERT_TRUE(geojson);
  EXPECT_EQ(geojson->GetLayer(0)->GetFeatureCount(), 2);
}

}  // namespace
}  // namespace irmosaic
