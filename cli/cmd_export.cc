// `irmosaic export`: the published store as one COG / GeoTIFF / GeoPackage in any CRS.
#include <gdal.h>

#include <iostream>

#include "args.h"
#include "commands.h"
#include "irmosaic/mosaic_export.h"

namespace irmosaic::cli {

int RunExport(int argc, char** argv) {
  Args args("export",
            "Exports the last published state of a store to one raster through GDAL (warp +\n"
            "translate), with overviews and coverage as an alpha band. Default: a Cloud\n"
            "Optimized GeoTIFF in the UTM zone of the flight origin, at the store's GSD.");
  args.Positional("STORE", "the store folder (holds manifest.json and mosaic.vrt)");
  args.Positional("OUT", "the output file");
  args.Option("-of", "output format: COG, GTiff or GPKG", "COG", "FORMAT");
  args.Option("--t_srs", "target CRS (EPSG:xxxx, WKT, PROJ); default: UTM zone of the origin", "",
              "SRS");
  args.Option("-co", "driver creation option, repeatable (e.g. -co COMPRESS=DEFLATE)", "",
              "KEY=VALUE");
  args.Option("-r", "resampling: near (keeps measured values), bilinear, cubic, average...", "near",
              "METHOD");
  args.Option("-tr", "target pixel size in target CRS units (0: the store's GSD)", "0", "RES");
  args.Flag("-q", "quiet: no progress bar");
  int exit_code = 0;
  if (!args.Parse(argc, argv, &exit_code)) return exit_code;

  ExportOptions options;
  options.format = args.Get("-of");
  options.target_srs = args.Get("--t_srs");
  options.creation_options = args.GetAll("-co");
  options.resampling = args.Get("-r");
  options.target_resolution_m = args.GetDouble("-tr");
  if (!args.Has("-q")) {
    options.progress = [](double fraction, const char* message) {
      return GDALTermProgress(fraction, message, nullptr) != 0;
    };
  }
  const ExportSummary s = ExportMosaic(args.Get("STORE"), args.Get("OUT"), options);
  std::cerr << "export: " << s.output_path << " (" << s.format << ", " << s.target_srs << "), "
            << s.width << " x " << s.height << " px of " << s.pixel_size << ", " << s.bands
            << " bands, " << s.overview_count << " overviews, store generation "
            << s.store_generation << ", " << s.seconds << " s\n";
  return 0;
}

}  // namespace irmosaic::cli
