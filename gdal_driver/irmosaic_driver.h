#pragma once

// The IRMOSAIC GDAL driver: opens an irmosaic store (a folder written by TileStore, or its
// manifest.json) read-only as one raster dataset with the store's levels as overviews.
// Built twice from the same code: the plug-in gdal_IRMOSAIC.so (GDAL_DRIVER_PATH) and an object
// library that tests and fuzzers link to register the driver in-process.

#include <cstddef>

extern "C" {

// Registers the driver with GDAL's driver manager; a no-op if already registered.
__attribute__((visibility("default"))) void GDALRegister_IRMOSAIC();

// Registers the driver, opens `manifest_path` (a store folder or its manifest.json) through it
// and reads one block of each band; returns 0 if opened and read, -1 otherwise. Never throws.
__attribute__((visibility("default"))) int IrmosaicDriverOpenForFuzzing(const char* manifest_path);

// Validates manifest bytes as the driver would (no file access); returns 0 if accepted, -1 if
// refused. Never throws.
__attribute__((visibility("default"))) int IrmosaicParseManifestForFuzzing(const char* data,
                                                                           size_t size);
}
