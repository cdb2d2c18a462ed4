// ExportMosaic: a store -> COG / GeoTIFF / GeoPackage in another CRS, read back through GDAL.
#include "irmosaic/mosaic_export.h"

#include <gdal.h>
#include <gtest/gtest.h>
#include <ogr_spatialref.h>
#include <unistd.h>

#include <GeographicLib/Geodesic.hpp>
#include <cstdlib>
#include <filesystem>
#include <opencv2/imgproc.hpp>

#include "irmosaic/error.h"
#include "irmosaic/local_frame.h"
#include "irmosaic/tile_store.h"
#include "test_data.h"

namespace irmosaic {
namespace {

namespace fs = std::filesystem;
constexpr double kLat0 = 47.2, kLon0 = 8.5, kGsd = 0.5;

struct Marker {
  cv::Point top_left;
  int value;
};
const std::vector<Marker> kMarkers = {
    {{-700, -300}, 1111}, {{250, 250}, 2222}, {{900, -650}, 3333}, {{-20, 800}, 4444}};
constexpr int kMarkerSize = 24;

fs::path MakeStore(const std::string& name, int tile_size = 512,
                   const std::vector<Marker>& markers = kMarkers) {
  const fs::path dir = fs::temp_directory_path() /
                       ("irmosaic_export_test_" + std::to_string(::getpid()) + "_" + name);
  fs::remove_all(dir);
  fs::create_directories(dir);
  TileStoreOptions options;
  options.path = (dir / "s.irmosaic").string();
  options.tile_size = tile_size;
  auto store = TileStore::Open(options, {kLat0, kLon0, kGsd, LocalFrame(kLat0, kLon0).CrsWkt()});
  for (const Marker& m : markers) {
    store->Paint(cv::Mat(kMarkerSize, kMarkerSize, CV_16U, cv::Scalar(m.value)),
                 cv::Mat(kMarkerSize, kMarkerSize, CV_32F, cv::Scalar(1.0f)), m.top_left);
  }
  store->Close();
  return dir;
}

double GeodesicMetres(const Eigen::Vector2d& lat_lon_a, const Eigen::Vector2d& lat_lon_b) {
  double s12 = 0;
  GeographicLib::Geodesic::WGS84().Inverse(lat_lon_a.x(), lat_lon_a.y(), lat_lon_b.x(),
                                           lat_lon_b.y(), s12);
  return s12;
}

// Checks an export: CRS, marker positions on the ground (through lat/lon), exact values.
void CheckExport(const fs::path& path, int expected_epsg, int expected_bands,
                 const std::vector<Marker>& markers = kMarkers) {
  GDALDatasetH ds = GDALOpen(path.c_str(), GA_ReadOnly);
  ASSERT_NE(ds, nullptr) << path;
  OGRSpatialReference srs, expected;
  srs.importFromWkt(GDALGetProjectionRef(ds));
  expected.importFromEPSG(expected_epsg);
  EXPECT_TRUE(srs.IsSame(&expected)) << GDALGetProjectionRef(ds);
  ASSERT_EQ(GDALGetRasterCount(ds), expected_bands);
  EXPECT_GE(GDALGetOverviewCount(GDALGetRasterBand(ds, 1)), 1);
  double gt[6];
  GDALGetGeoTransform(ds, gt);
  const int w = GDALGetRasterXSize(ds), h = GDALGetRasterYSize(ds);
  cv::Mat data(h, w, CV_32F), covered;
  ASSERT_EQ(GDALRasterIO(GDALGetRasterBand(ds, 1), GF_Read, 0, 0, w, h, data.ptr(), w, h,
                         GDT_Float32, 0, 0),
            CE_None);
  if (expected_bands == 2) {
    cv::Mat alpha(h, w, CV_32F);
    ASSERT_EQ(GDALRasterIO(GDALGetRasterBand(ds, 2), GF_Read, 0, 0, w, h, alpha.ptr(), w, h,
                           GDT_Float32, 0, 0),
              CE_None);
    covered = alpha > 0;
  } else {
    int has_nodata = 0;
    const double nodata = GDALGetRasterNoDataValue(GDALGetRasterBand(ds, 1), &has_nodata);
    ASSERT_TRUE(has_nodata);
    covered = data != nodata;
  }
  GDALClose(ds);

  OGRSpatialReference wgs84;
  wgs84.importFromEPSG(4326);
  wgs84.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
  srs.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
  OGRCoordinateTransformation* to_wgs84 = OGRCreateCoordinateTransformation(&srs, &wgs84);
  const PlaneToGeographic plane_to_geo{LocalFrame(kLat0, kLon0)};
  const MosaicGrid grid{kGsd};
  int covered_pixels = 0;
  for (const Marker& m : markers) {
    const cv::Mat hit = data == m.value;
    const cv::Moments moments = cv::moments(hit, true);
    // Nearest-neighbour resampling keeps the area within a pixel row/column per side.
    EXPECT_NEAR(moments.m00, kMarkerSize * kMarkerSize, 4.0 * kMarkerSize) << m.value;
    covered_pixels += static_cast<int>(moments.m00);
    double x = gt[0] + (moments.m10 / moments.m00 + 0.5) * gt[1];
    double y = gt[3] + (moments.m01 / moments.m00 + 0.5) * gt[5];
    ASSERT_TRUE(to_wgs84->Transform(1, &x, &y));
    const double half = (kMarkerSize - 1) / 2.0;
    const Eigen::Vector2d truth = plane_to_geo.LatLonFromPlane(
        grid.PlaneFromPixel({m.top_left.x + half, m.top_left.y + half}));
    EXPECT_LT(GeodesicMetres({y, x}, truth), kGsd) << "marker " << m.value;
  }
  OGRCoordinateTransformation::DestroyCT(to_wgs84);
  // Near resampling invents no values: every covered pixel holds a marker's value.
  EXPECT_EQ(cv::countNonZero(covered), covered_pixels);
}

TEST(MosaicExportTest, UtmEpsgFollowsTheZoneRules) {
  EXPECT_EQ(UtmEpsgFor(47.2, 8.5), 32632);
  EXPECT_EQ(UtmEpsgFor(-33.9, 18.4), 32734);
  EXPECT_EQ(UtmEpsgFor(60.4, 5.3), 32632);   // Bergen: Norway exception.
  EXPECT_EQ(UtmEpsgFor(78.2, 15.6), 32633);  // Svalbard.
  EXPECT_EQ(UtmEpsgFor(10.0, -179.9), 32601);
  EXPECT_EQ(UtmEpsgFor(10.0, 180.0), 32601);
}

TEST(MosaicExportTest, DefaultCogInUtmPlacesContentWithinOneGsdWithExactValues) {
  const fs::path dir = MakeStore("cog");
  ExportOptions options;
  double last_progress = -1.0;
  bool monotonic = true;
  options.progress = [&](double fraction, const char*) {
    monotonic = monotonic && fraction >= last_progress;
    last_progress = fraction;
    return true;
  };
  const ExportSummary summary =
      ExportMosaic((dir / "s.irmosaic").string(), (dir / "out.tif").string(), options);
  EXPECT_EQ(summary.target_srs, "EPSG:32632");
  EXPECT_EQ(summary.store_generation, 1);
  EXPECT_GE(summary.overview_count, 1);
  EXPECT_TRUE(monotonic);
  EXPECT_DOUBLE_EQ(last_progress, 1.0);
  CheckExport(dir / "out.tif", 32632, 2);
  GDALDatasetH ds = GDALOpen((dir / "out.tif").c_str(), GA_ReadOnly);
  EXPECT_STREQ(GDALGetMetadataItem(ds, "LAYOUT", "IMAGE_STRUCTURE"), "COG");
  EXPECT_STREQ(GDALGetMetadataItem(ds, "COMPRESSION", "IMAGE_STRUCTURE"), "ZSTD");
  GDALClose(ds);
}

// mosaic.vrt's extent grows in steps (a sixteenth of the span, docs/store.md): here 38 tiles
// of 64 px painted across, 40 in the VRT. The export covers the painted tiles only.
TEST(MosaicExportTest, ExportCoversThePaintedTilesNotThePaddedVrtExtent) {
  const std::vector<Marker> wide = {
      {{-1300, -300}, 1111}, {{250, 250}, 2222}, {{900, -650}, 3333}, {{1030, 800}, 4444}};
  constexpr int kTile = 64;
  const fs::path dir = MakeStore("padded", kTile, wide);
  GDALAllRegister();
  GDALDatasetH vrt = GDALOpen((dir / "s.irmosaic/mosaic.vrt").c_str(), GA_ReadOnly);
  ASSERT_NE(vrt, nullptr);
  EXPECT_EQ(GDALGetRasterXSize(vrt), 40 * kTile);  // Tile columns -22 .. 17 (painted -21 .. 16).
  EXPECT_EQ(GDALGetRasterYSize(vrt), 24 * kTile);  // Tile rows -11 .. 12: exact below 32.
  GDALClose(vrt);
  ExportOptions options;
  options.format = "GTiff";
  ExportMosaic((dir / "s.irmosaic").string(), (dir / "out.tif").string(), options);
  CheckExport(dir / "out.tif", 32632, 2, wide);
  GDALDatasetH out = GDALOpen((dir / "out.tif").c_str(), GA_ReadOnly);
  ASSERT_NE(out, nullptr);
  // UTM against the tangent plane: a scale within 1e-3 and a rotation of ~0.4 degrees here,
  // which widens the bounding box by sin(0.4 deg) x the height (~11 px): well under a tile.
  EXPECT_NEAR(GDALGetRasterXSize(out), 38 * kTile, 16);
  EXPECT_NEAR(GDALGetRasterYSize(out), 24 * kTile, 24);
  GDALClose(out);
}

TEST(MosaicExportTest, GtiffAndGpkgWithOptionsInAnotherCrs) {
  const fs::path dir = MakeStore("formats");
  ExportOptions gtiff;
  gtiff.format = "GTiff";
  gtiff.target_srs = "EPSG:25832";  // ETRS89 / UTM 32N.
  gtiff.creation_options = {"COMPRESS=DEFLATE"};
  ExportMosaic((dir / "s.irmosaic").string(), (dir / "out.tif").string(), gtiff);
  CheckExport(dir / "out.tif", 25832, 2);
  GDALDatasetH ds = GDALOpen((dir / "out.tif").c_str(), GA_ReadOnly);
  EXPECT_STREQ(GDALGetMetadataItem(ds, "COMPRESSION", "IMAGE_STRUCTURE"), "DEFLATE");
  GDALClose(ds);

  ExportOptions gpkg;
  gpkg.format = "GPKG";
  ExportMosaic((dir / "s.irmosaic").string(), (dir / "out.gpkg").string(), gpkg);
  CheckExport(dir / "out.gpkg", 32632, 1);
}

TEST(MosaicExportTest, BadInputsAreErrorsThatNameTheFix) {
  const fs::path dir = MakeStore("bad");
  ExportOptions options;
  options.format = "JPEG";
  EXPECT_THROW(ExportMosaic((dir / "s.irmosaic").string(), (dir / "x.jpg").string(), options),
               InputError);
  options.format = "COG";
  options.target_srs = "EPSG:999999";
  EXPECT_THROW(ExportMosaic((dir / "s.irmosaic").string(), (dir / "x.tif").string(), options),
               InputError);
  options.target_srs.clear();
  EXPECT_THROW(ExportMosaic((dir / "nothing").string(), (dir / "x.tif").string(), options),
               InputError);
  EXPECT_THROW(
      ExportMosaic((dir / "s.irmosaic").string(), (dir / "no" / "x.tif").string(), options),
      OutputError);
  EXPECT_FALSE(fs::exists(dir / "x.tif"));
}

TEST(MosaicExportTest, CommandLineExportsWithGdalStyleOptions) {
  const fs::path dir = MakeStore("cli");
  const std::string cli = testing::CliPath();
  const std::string ok = cli + " export " + (dir / "s.irmosaic").string() + " " +
                         (dir / "cli.tif").string() + " -of GTiff --t_srs EPSG:32632 -co " +
                         "COMPRESS=LZW -q 2>/dev/null";
  ASSERT_EQ(std::system(ok.c_str()), 0) << ok;
  CheckExport(dir / "cli.tif", 32632, 2);
  const std::string bad = cli + " export " + (dir / "s.irmosaic").string() + " " +
                          (dir / "bad.tif").string() + " -of PNG -q 2>/dev/null";
  const int status = std::system(bad.c_str());
  EXPECT_EQ(WEXITSTATUS(status), 1);
  EXPECT_FALSE(fs::exists(dir / "bad.tif"));
}

}  // namespace
}  // namespace irmosaic
