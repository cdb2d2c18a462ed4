// libFuzzer target: the IRMOSAIC GDAL driver's Identify/Open on manifest bytes. The input is
// written as manifest.json of a scratch store folder that also holds a few real tiles (16 x 16,
// each data type), a tile that is not a GeoTIFF, a tile symlinked out of the store, an overview
// tile and a frames.gpkg, so a manifest the mutator keeps valid reaches the block reads, the
// overviews and the footprints layer. The driver is registered in-process (as the tests do).
// Bad input must end in a refusal (nullptr or CE_Failure); never a crash, a leak, a hang, a huge
// allocation or a read outside the store.
#include <dlfcn.h>
#include <gdal_priv.h>
#include <ogrsf_frmts.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

#include "fuzz_util.h"
#include "irmosaic_driver.h"

namespace {

namespace fs = std::filesystem;

// A two-band T x T tile of `type` as the store writes it (data, alpha); no CRS needed.
void WriteTile(const fs::path& path, GDALDataType type) {
  fs::create_directories(path.parent_path());
  GDALDriver* gtiff = GetGDALDriverManager()->GetDriverByName("GTiff");
  GDALDatasetUniquePtr tile(gtiff->Create(path.c_str(), 16, 16, 2, type, nullptr));
  std::vector<double> values(16 * 16, 200.0);
  for (int b = 1; b <= 2; ++b) {
    (void)tile->GetRasterBand(b)->RasterIO(GF_Write, 0, 0, 16, 16, values.data(), 16, 16,
                                           GDT_Float64, 0, 0, nullptr);
  }
}

// frames.gpkg with layer "frames" and two footprints, as TileStore writes it.
void WriteFrames(const fs::path& path) {
  GDALDriver* gpkg = GetGDALDriverManager()->GetDriverByName("GPKG");
  GDALDatasetUniquePtr ds(gpkg->Create(path.c_str(), 0, 0, 0, GDT_Unknown, nullptr));
  OGRLayer* layer = ds->CreateLayer("frames", nullptr, wkbPolygon, nullptr);
  OGRFieldDefn time_field("time_s", OFTReal);
  layer->CreateField(&time_field);
  for (int i = 0; i < 2; ++i) {
    OGRFeature feature(layer->GetLayerDefn());
    feature.SetField("time_s", 0.04 * i);
    OGRGeometry* polygon = nullptr;
    const char* wkt = "POLYGON ((0 0,10 0,10 -10,0 -10,0 0))";
    OGRGeometryFactory::createFromWkt(wkt, nullptr, &polygon);
    feature.SetGeometryDirectly(polygon);
    (void)layer->CreateFeature(&feature);
  }
}

// The scratch store folder, populated once per process.
const fs::path& Store() {
  static const fs::path store = [] {
    // This build's driver first: a gdal_IRMOSAIC.so installed in GDAL's plug-in folder would
    // otherwise take the name and the fuzzer would exercise that uninstrumented copy.
    GDALRegister_IRMOSAIC();
    GDALAllRegister();
    Dl_info where;
    GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("IRMOSAIC");
    if (driver == nullptr || ::dladdr(reinterpret_cast<void*>(driver->pfnOpen), &where) == 0 ||
        std::string(where.dli_fname).find("gdal_IRMOSAIC") != std::string::npos) {
      std::fprintf(stderr, "gdal_driver_fuzzer: the IRMOSAIC driver is not this build's\n");
      std::abort();
    }
    // GDAL's messages for refused manifests would drown libFuzzer's log.
    CPLPushErrorHandler(CPLQuietErrorHandler);
    const fs::path root = irmosaic::fuzz::ScratchDir();
    const fs::path dir = root / "store.irmosaic";
    fs::remove_all(dir);
    WriteTile(dir / "tiles/0/0_0.tif", GDT_Byte);
    WriteTile(dir / "tiles/0/0_1.tif", GDT_UInt16);
    WriteTile(dir / "tiles/0/-1_0.tif", GDT_Float32);
    WriteTile(dir / "tiles/1/0_0.tif", GDT_Byte);
    WriteTile(dir / "tiles/2/0_0.tif", GDT_Byte);
    // A tile that is not a GeoTIFF, and one that leads out of the store.
    irmosaic::fuzz::WriteBytes(dir / "tiles/0/1_1.tif", reinterpret_cast<const uint8_t*>("II*"), 3);
    WriteTile(root / "outside.tif", GDT_Byte);
    fs::create_symlink(root / "outside.tif", dir / "tiles/0/1_0.tif");
    WriteFrames(dir / "frames.gpkg");
    return dir;
  }();
  return store;
}

// Reads a small window of every band of `ds` and of its overviews.
void ReadSome(GDALDataset* ds) {
  std::vector<double> buffer(32 * 32);
  const int w = std::min(32, ds->GetRasterXSize()), h = std::min(32, ds->GetRasterYSize());
  for (int b = 1; b <= ds->GetRasterCount(); ++b) {
    GDALRasterBand* band = ds->GetRasterBand(b);
    (void)band->RasterIO(GF_Read, 0, 0, w, h, buffer.data(), w, h, GDT_Float64, 0, 0, nullptr);
    for (int o = 0; o < band->GetOverviewCount(); ++o) {
      GDALRasterBand* overview = band->GetOverview(o);
      const int ow = std::min(32, overview->GetXSize()), oh = std::min(32, overview->GetYSize());
      (void)overview->RasterIO(GF_Read, 0, 0, ow, oh, buffer.data(), ow, oh, GDT_Float64, 0, 0,
                               nullptr);
    }
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const fs::path& store = Store();
  irmosaic::fuzz::WriteBytes(store / "manifest.json", data, size);
  // The folder as QGIS and gdalinfo name it; raster and vector, as a generic client asks.
  const char* const allowed[] = {"IRMOSAIC", nullptr};
  GDALDatasetUniquePtr ds(GDALDataset::Open(store.c_str(),
                                            GDAL_OF_RASTER | GDAL_OF_VECTOR | GDAL_OF_READONLY,
                                            allowed, nullptr, nullptr));
  if (!ds) return 0;
  (void)ds->GetMetadata();
  double gt[6];
  (void)ds->GetGeoTransform(gt);
  ReadSome(ds.get());
  for (int i = 0; i < ds->GetLayerCount(); ++i) {
    OGRLayer* layer = ds->GetLayer(i);
    (void)layer->GetFeatureCount();
    layer->ResetReading();
    for (int n = 0; n < 3; ++n) {
      OGRFeatureUniquePtr feature(layer->GetNextFeature());
      if (!feature) break;
    }
  }
  return 0;
}
