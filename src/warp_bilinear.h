#pragma once
// Private helper of the orthorectifier (src/orthorectify.cc): bilinear projective resampling
// of 8- and 16-bit frames. OpenCV 4.6 warps 16-bit images with scalar code (its remap has vector
// code for 8-bit images only), and for either depth quantises positions to 1/32 px and builds
// fixed-point maps before remapping; this computes each position in float and samples the four
// neighbours with AVX2 where the CPU has it, by gather instructions or by eight scalar loads,
// whichever this CPU runs faster (measured once, at the first warp). The scalar path computes every
// pixel with the same float operations in the same order (no fused multiply-add), so the output
// does not depend on the CPU. Not installed.

#include <opencv2/core.hpp>

namespace irmosaic::warp {

// dst(x, y) = src(m (x, y, 1)) (homogeneous), bilinear, sample positions clamped to src (as
// BORDER_REPLICATE), rounded to the nearest integer (ties to even). m = src_from_dst.
// src: CV_8UC1 or CV_16UC1 of at least 2 x 2 pixels and less than 2 GiB; dst: the same type,
// its size is the output's (written in place, any step). Returns false, dst untouched, for
// anything else.
bool WarpBilinear(const cv::Mat& src, const cv::Matx33d& src_from_dst, cv::Mat* dst);

// Tests: the scalar path alone (the AVX2 one is chosen by simd::Avx2()).
bool WarpBilinearScalar(const cv::Mat& src, const cv::Matx33d& src_from_dst, cv::Mat* dst);

// How the AVX2 path reads a pixel pair per lane: AVX2's gather instruction, or eight scalar
// loads put together. Same values; on some Intel cores the gather is much the slower.
enum class GatherPath { kHardware, kEmulated };

// Tests and benchmarks: the AVX2 path with the given gather. False (dst untouched) when the CPU
// has no AVX2 (or it is disabled) or WarpBilinear would refuse the input.
bool WarpBilinearAvx2(const cv::Mat& src, const cv::Matx33d& src_from_dst, cv::Mat* dst,
                      GatherPath gather);

// The gather WarpBilinear uses on this machine: "hardware", "emulated", or "none" without
// AVX2. The first call may run the measurement (1-2 ms, once per process); IRMOSAIC_WARP_GATHER =
// hardware | emulated in the environment fixes the choice.
const char* GatherPathName();

}  // namespace irmosaic::warp
