#pragma once

#include <cstdint>

#include "irmosaic/export.h"

// Test seams of MapFusion: points where tests/map_fusion_test.cc holds one thread so that a race
// of the hand-over between Push and a running solve happens on every run, not once in many. Not
// part of the API (not installed). Unset, the default, each costs one atomic load.
namespace irmosaic::fusion_testing {

// Called on the optimizer thread once a background solve has taken its snapshot of frames
// [first_index, last_index] and released the lock, before it solves and publishes.
using SolveSnapshotHook = void (*)(int64_t first_index, int64_t last_index);
// Called on Push's thread once it has painted frame `index` as the frame left the fusion with
// its paint lagging (the settled re-render), before it checks whether a solve moved the frame
// meanwhile.
using SettledPaintHook = void (*)(int64_t index);

IRMOSAIC_EXPORT void SetSolveSnapshotHook(SolveSnapshotHook hook);
IRMOSAIC_EXPORT void SetSettledPaintHook(SettledPaintHook hook);

}  // namespace irmosaic::fusion_testing
