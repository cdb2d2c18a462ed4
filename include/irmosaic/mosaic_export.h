#pragma once

#include <functional>
#include <string>
#include <vector>

#include "irmosaic/export.h"

namespace irmosaic {

// Configuration of ExportMosaic; option names follow gdalwarp / gdal_translate.
struct ExportOptions {
  std::string format = "COG";  // -of: COG, GTiff or GPKG.
  std::string target_srs;  // --t_srs: "EPSG:32632", WKT, PROJ...; empty: UTM zone of the origin.
  std::vector<std::string> creation_options;  // -co KEY=VALUE, passed to the driver.
  std::string resampling = "near";   // -r: near keeps measured values; bilinear, cubic, average...
  double target_resolution_m = 0.0;  // -tr in target CRS units; 0: the store's GSD.
  // Progress in [0, 1] with a message; return false to cancel. Empty: silent.
  std::function<bool(double fraction, const char* message)> progress;

  // True if usable; otherwise *error says which option is wrong and why.
  bool IsValid(std::string* error) const;
};

// What an export produced, for printing.
struct ExportSummary {
  std::string output_path;
  std::string format;
  std::string target_srs;     // As given to GDAL (e.g. "EPSG:32632").
  int width = 0, height = 0;  // Pixels.
  int bands = 0;              // Data band (+ alpha band, except GPKG of 16/32-bit data).
  int overview_count = 0;
  double pixel_size = 0.0;       // Target CRS units.
  int64_t store_generation = 0;  // Generation of the store that was exported.
  double seconds = 0.0;
};

// EPSG code of the WGS84 UTM zone holding (lat, lon): 326zz north, 327zz south (with the
// Norway and Svalbard exceptions).
IRMOSAIC_EXPORT int UtmEpsgFor(double lat_deg, double lon_deg);

// Exports the published state of a store (its mosaic.vrt) to one raster in any CRS through
// GDALWarp and GDALTranslate, with overviews. Coverage becomes an alpha band (nodata for
// 16/32-bit GeoPackage, which has no alpha). Throws InputError (no store, bad options) or
// OutputError (cannot write) naming the path and the fix. The output is written to a temporary
// name and renamed, so a failed export leaves no partial file.
IRMOSAIC_EXPORT ExportSummary ExportMosaic(const std::string& store_path,
                                           const std::string& output_path,
                                           const ExportOptions& options);

}  // namespace irmosaic
