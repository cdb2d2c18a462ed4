#pragma once
// Tests' stand-in for another program holding a store's frames.gpkg locked (a script's
// transaction, a GIS editing the footprints): a GDAL transaction with a write in it, which holds
// SQLite's write lock until it is rolled back. For a child process of the test (tile_store_test,
// run_cli_test).

#include <cpl_error.h>
#include <gdal_priv.h>

#include <string>

namespace irmosaic::testing {

// Opens `gpkg` for update and takes its write lock; the open dataset holding it, or nullptr
// (nothing left open) when the lock could not be taken (file missing, another writer).
inline GDALDataset* LockFramesGpkg(const std::string& gpkg) {
  GDALDataset* ds = GDALDataset::Open(gpkg.c_str(), GDAL_OF_VECTOR | GDAL_OF_UPDATE);
  CPLErrorReset();
  if (ds != nullptr && ds->StartTransaction() == OGRERR_NONE) {
    // A write in the transaction takes SQLite's write lock until the rollback (also when no
    // row matches).
    ds->ExecuteSQL("UPDATE frames SET status = 'held by another process' WHERE fid = 1", nullptr,
                   nullptr);
    if (CPLGetLastErrorType() == CE_None) return ds;
    ds->RollbackTransaction();
  }
  if (ds != nullptr) GDALClose(ds);
  return nullptr;
}

// Lets go of a lock LockFramesGpkg took: rolls the write back and closes the file.
inline void UnlockFramesGpkg(GDALDataset* ds) {
  ds->RollbackTransaction();
  GDALClose(ds);
}

}  // namespace irmosaic::testing
