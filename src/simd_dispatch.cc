#include "simd_dispatch.h"

#include <atomic>
#include <cstdlib>
#include <cstring>

namespace irmosaic::simd {
namespace {

bool CpuHasAvx2() {
#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
  __builtin_cpu_init();  // Needed when first asked before main (static initialisers).
  return __builtin_cpu_supports("avx2");
#else
  return false;
#endif
}

// IRMOSAIC_DISABLE_AVX2=1 in the environment keeps the baseline paths (for comparisons; the
// results are the same either way).
bool Avx2AllowedByEnvironment() {
  const char* value = std::getenv("IRMOSAIC_DISABLE_AVX2");
  return value == nullptr || *value == '\0' || std::strcmp(value, "0") == 0;
}

std::atomic<bool> g_avx2_allowed{Avx2AllowedByEnvironment()};

}  // namespace

bool Avx2() {
  static const bool has = CpuHasAvx2();
  return has && g_avx2_allowed.load(std::memory_order_relaxed);
}

bool SetAvx2Allowed(bool allowed) { return g_avx2_allowed.exchange(allowed); }

}  // namespace irmosaic::simd
