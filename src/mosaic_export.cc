// `irmosaic export`: the published store -> one raster in any CRS, through GDALWarp/GDALTranslate.
#include "irmosaic/mosaic_export.h"

#include <cpl_conv.h>
#include <cpl_error.h>
#include <cpl_string.h>
#include <gdal.h>
#include <gdal_utils.h>
#include <ogr_spatialref.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <sstream>

#include "irmosaic/error.h"
#include "store_internal.h"

namespace irmosaic {

namespace fs = std::filesystem;

bool ExportOptions::IsValid(std::string* error) const {
  std::string problem;
  if (format != "COG" && format != "GTiff" && format != "GPKG") {
    problem = "-of " + format + ": supported formats are COG, GTiff and GPKG";
  } else if (!(target_resolution_m >= 0.0) || !std::isfinite(target_resolution_m)) {
    problem = "-tr must be a positive resolution (or 0 for the store's GSD)";
  } else if (resampling.empty()) {
    problem = "-r needs a GDAL resampling method (near, bilinear, cubic, average...)";
  }
  for (const std::string& option : creation_options) {
    if (problem.empty() && option.find('=') == std::string::npos) {
      problem = "-co " + option + ": creation options are KEY=VALUE";
    }
  }
  if (!problem.empty() && error) *error = problem;
  return problem.empty();
}

int UtmEpsgFor(double lat_deg, double lon_deg) {
  const double lon = std::fmod(std::fmod(lon_deg + 180.0, 360.0) + 360.0, 360.0) - 180.0;
  int zone = static_cast<int>(std::floor((lon + 180.0) / 6.0)) + 1;
  zone = std::clamp(zone, 1, 60);
  if (lat_deg >= 56.0 && lat_deg < 64.0 && lon >= 3.0 && lon < 12.0) zone = 32;  // Norway.
  if (lat_deg >= 72.0 && lat_deg < 84.0 && lon >= 0.0 && lon < 42.0) {           // Svalbard.
    zone = lon < 9.0 ? 31 : lon < 21.0 ? 33 : lon < 33.0 ? 35 : 37;
  }
  return (lat_deg >= 0.0 ? 32600 : 32700) + zone;
}

namespace {

// Keeps the last GDAL failure of this thread while alive (GDAL prints nothing meanwhile); the
// last one is the cause, earlier ones are often PROJ noise about points off the projection.
class ErrorCapture {
 public:
  ErrorCapture() { CPLPushErrorHandlerEx(&Handler, this); }
  ~ErrorCapture() { CPLPopErrorHandler(); }
  std::string message() const { return message_.empty() ? "GDAL failed" : message_; }

 private:
  static void CPL_STDCALL Handler(CPLErr level, CPLErrorNum, const char* text) {
    auto* self = static_cast<ErrorCapture*>(CPLGetErrorHandlerUserData());
    if (level >= CE_Failure) self->message_ = text ? text : "";
  }
  std::string message_;
};

struct Progress {
  const ExportOptions* options;
  double from, to;
  std::string message;
};

int CPL_STDCALL ProgressTrampoline(double fraction, const char*, void* data) {
  const auto* p = static_cast<const Progress*>(data);
  if (!p->options->progress) return TRUE;
  return p->options->progress(p->from + fraction * (p->to - p->from), p->message.c_str()) ? TRUE
                                                                                          : FALSE;
}

bool HasKey(const std::vector<std::string>& options, const std::string& key) {
  for (const std::string& option : options) {
    if (EQUAL(option.substr(0, option.find('=')).c_str(), key.c_str())) return true;
  }
  return false;
}

std::vector<std::string> CreationOptionsFor(const std::string& format, PixelType type,
                                            const std::vector<std::string>& user) {
  std::vector<std::string> defaults;
  if (format == "COG") {
    defaults = {"COMPRESS=ZSTD", "PREDICTOR=YES", "BLOCKSIZE=512", "OVERVIEW_RESAMPLING=AVERAGE",
                "BIGTIFF=IF_SAFER"};
  } else if (format == "GTiff") {
    defaults = {"TILED=YES",
                "BLOCKXSIZE=512",
                "BLOCKYSIZE=512",
                "COMPRESS=ZSTD",
                type == PixelType::kFloat32 ? "PREDICTOR=3" : "PREDICTOR=2",
                "BIGTIFF=IF_SAFER"};
  }
  std::vector<std::string> out = user;
  for (const std::string& option : defaults) {
    if (!HasKey(user, option.substr(0, option.find('=')))) out.push_back(option);
  }
  return out;
}

}  // namespace

ExportSummary ExportMosaic(const std::string& store_path, const std::string& output_path,
                           const ExportOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  std::string problem;
  if (!options.IsValid(&problem)) {
    throw InputError({output_path, 0, 0, "export options"}, problem, "fix the option named");
  }
  const fs::path root(store_path);
  const store::Manifest manifest = store::ReadManifest(root / "manifest.json");
  if (manifest.levels.empty() || manifest.levels[0].empty()) {
    throw InputError({store_path, 0, 0, ""}, "the store has no published tiles yet",
                     "export once the run has published its first frames");
  }
  GDALAllRegister();
  ExportSummary summary;
  summary.output_path = output_path;
  summary.format = options.format;
  summary.store_generation = manifest.generation;
  summary.target_srs = options.target_srs.empty()
                           ? "EPSG:" + std::to_string(UtmEpsgFor(manifest.georef.origin_lat_deg,
                                                                 manifest.georef.origin_lon_deg))
                           : options.target_srs;
  OGRSpatialReference target;
  if (target.SetFromUserInput(summary.target_srs.c_str()) != OGRERR_NONE) {
    throw InputError({summary.target_srs, 0, 0, "--t_srs"}, "not a coordinate system GDAL knows",
                     "give an EPSG code such as EPSG:32632, or WKT / PROJ text");
  }
  // Pixel size: the store's GSD in metres; for a geographic target, its angle on the Earth.
  double resolution = options.target_resolution_m;
  if (resolution == 0.0) {
    resolution = manifest.georef.gsd_m;
    if (target.IsGeographic()) resolution = manifest.georef.gsd_m / 111320.0;
  }
  summary.pixel_size = resolution;

  ErrorCapture errors;
  GDALDatasetH source = GDALOpen((root / "mosaic.vrt").c_str(), GA_ReadOnly);
  if (source == nullptr) {
    throw InputError({(root / "mosaic.vrt").string(), 0, 0, ""},
                     "GDAL cannot open the store's index: " + errors.message(),
                     "check the store folder");
  }
  GDALDatasetH whole = nullptr;  // mosaic.vrt when `source` is a window of it.
  // mosaic.vrt's extent grows in steps (store::VrtBounds): the export covers the painted tiles
  // only, a window of it (whole pixels: both extents are whole tiles of the same grid).
  {
    double gt[6];
    GDALGetGeoTransform(source, gt);
    const store::TileBounds painted = manifest.levels[0].bounds();
    const int64_t t = manifest.tile_size;
    double painted_gt[6];
    store::TileGeoTransform(manifest.georef.gsd_m, manifest.tile_size, 0,
                            {painted.row0, painted.col0}, painted_gt);
    const int64_t x = std::llround((painted_gt[0] - gt[0]) / gt[1]);
    const int64_t y = std::llround((painted_gt[3] - gt[3]) / gt[5]);
    const int64_t w = (painted.col1 - painted.col0) * t, h = (painted.row1 - painted.row0) * t;
    if (x != 0 || y != 0 || w != GDALGetRasterXSize(source) || h != GDALGetRasterYSize(source)) {
      CPLStringList window_args;
      window_args.AddString("-of");
      window_args.AddString("VRT");
      window_args.AddString("-srcwin");
      for (const int64_t v : {x, y, w, h}) window_args.AddString(std::to_string(v).c_str());
      GDALTranslateOptions* window_options = GDALTranslateOptionsNew(window_args.List(), nullptr);
      int window_error = FALSE;
      GDALDatasetH window =
          window_options ? GDALTranslate("", source, window_options, &window_error) : nullptr;
      GDALTranslateOptionsFree(window_options);
      if (window == nullptr) {
        GDALClose(source);
        throw InputError(
            {(root / "mosaic.vrt").string(), 0, 0, ""},
            "GDAL cannot take the painted window of the store's index: " + errors.message(),
            "check the store folder (manifest.json and mosaic.vrt of one store)");
      }
      whole = source;  // Closed after the window, which reads through it.
      source = window;
    }
  }
  // 16/32-bit GeoPackage rasters have no alpha: coverage becomes nodata there.
  const bool nodata_instead_of_alpha =
      options.format == "GPKG" && manifest.type != PixelType::kByte;
  const std::string res = CPLSPrintf("%.17g", resolution);
  CPLStringList warp_args;
  for (const char* arg : {"-of", "VRT", "-t_srs", summary.target_srs.c_str(), "-r",
                          options.resampling.c_str(), "-tr", res.c_str(), res.c_str(), "-tap"}) {
    warp_args.AddString(arg);
  }
  if (nodata_instead_of_alpha) {
    warp_args.AddString("-srcalpha");
    warp_args.AddString("-dstnodata");
    warp_args.AddString(manifest.type == PixelType::kFloat32 ? "nan" : "65535");
  } else {
    warp_args.AddString("-dstalpha");
  }
  GDALWarpAppOptions* warp_options = GDALWarpAppOptionsNew(warp_args.List(), nullptr);
  int usage_error = FALSE;
  GDALDatasetH warped =
      warp_options ? GDALWarp("", nullptr, 1, &source, warp_options, &usage_error) : nullptr;
  GDALWarpAppOptionsFree(warp_options);
  if (warped == nullptr) {
    GDALClose(source);
    if (whole != nullptr) GDALClose(whole);
    throw InputError({summary.target_srs, 0, 0, "--t_srs"},
                     "GDAL cannot reproject the mosaic: " + errors.message(),
                     "check --t_srs, -r and -tr");
  }

  const fs::path output(output_path);
  const fs::path temp =
      output.parent_path() / ("." + output.stem().string() + ".tmp" + std::to_string(::getpid()) +
                              output.extension().string());
  const bool builds_own_overviews = options.format == "COG";
  Progress translate_progress{&options, 0.0, builds_own_overviews ? 1.0 : 0.7,
                              "writing " + output_path};
  CPLStringList translate_args;
  translate_args.AddString("-of");
  translate_args.AddString(options.format.c_str());
  if (nodata_instead_of_alpha) {
    translate_args.AddString("-b");  // The warped alpha band stays behind; nodata marks coverage.
    translate_args.AddString("1");
  }
  for (const std::string& option :
       CreationOptionsFor(options.format, manifest.type, options.creation_options)) {
    translate_args.AddString("-co");
    translate_args.AddString(option.c_str());
  }
  GDALTranslateOptions* translate_options = GDALTranslateOptionsNew(translate_args.List(), nullptr);
  GDALTranslateOptionsSetProgress(translate_options, ProgressTrampoline, &translate_progress);
  GDALDatasetH out = GDALTranslate(temp.c_str(), warped, translate_options, &usage_error);
  GDALTranslateOptionsFree(translate_options);
  std::string failure;
  if (out == nullptr) failure = errors.message();
  if (out != nullptr && !builds_own_overviews) {
    // Overviews down to one block, averaging covered pixels.
    std::vector<int> factors;
    for (int f = 2; GDALGetRasterXSize(out) / f >= 256 || GDALGetRasterYSize(out) / f >= 256;
         f *= 2) {
      factors.push_back(f);
    }
    Progress overview_progress{&options, 0.7, 1.0, "overviews"};
    if (!factors.empty() &&
        GDALBuildOverviews(out, "AVERAGE", static_cast<int>(factors.size()), factors.data(), 0,
                           nullptr, ProgressTrampoline, &overview_progress) != CE_None) {
      failure = errors.message();
    }
  }
  if (out != nullptr) {
    summary.width = GDALGetRasterXSize(out);
    summary.height = GDALGetRasterYSize(out);
    summary.bands = GDALGetRasterCount(out);
    GDALClose(out);
  }
  GDALClose(warped);
  GDALClose(source);
  if (whole != nullptr) GDALClose(whole);
  std::error_code error;
  if (!failure.empty()) {
    fs::remove(temp, error);
    throw OutputError("cannot write " + output_path + ": " + failure +
                      ". Fix: check the folder, free disk space, or check -co options");
  }
  fs::rename(temp, output, error);
  if (error) {
    fs::remove(temp, error);
    throw OutputError("cannot rename the export into " + output_path + ": " + error.message() +
                      ". Fix: check the folder's permissions");
  }
  // Count overviews as a reader will see them.
  if (GDALDatasetH check = GDALOpen(output.c_str(), GA_ReadOnly)) {
    summary.overview_count = GDALGetOverviewCount(GDALGetRasterBand(check, 1));
    GDALClose(check);
  }
  summary.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return summary;
}

}  // namespace irmosaic
