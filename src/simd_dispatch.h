#pragma once
// Private: run-time choice of vector code built for instruction sets beyond the baseline the
// library is compiled for (x86-64: SSE2). Each wider path computes every output as its
// baseline path does, operation for operation (no fused multiply-add), so results do not
// depend on the CPU. Not installed.

namespace irmosaic::simd {

// True when the CPU has AVX2, unless IRMOSAIC_DISABLE_AVX2 is set (to anything but 0) in the
// environment or SetAvx2Allowed(false) was called.
bool Avx2();

// Tests: false forces the baseline paths, true allows AVX2 again where the CPU has it.
// Returns the previous setting.
bool SetAvx2Allowed(bool allowed);

}  // namespace irmosaic::simd
