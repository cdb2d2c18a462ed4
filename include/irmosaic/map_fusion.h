#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "irmosaic/camera.h"
#include "irmosaic/export.h"
#include "irmosaic/orthorectify.h"

namespace irmosaic {

// Where one frame sits on the mosaic, as published (the latest estimate).
struct FramePlacement {
  int64_t index = -1;
  double time_s = 0.0;
  Eigen::Matrix3d mosaic_from_image = Eigen::Matrix3d::Identity();  // Undistorted px -> mosaic px.
  Eigen::Matrix3d pos_mosaic_from_image = Eigen::Matrix3d::Identity();  // From POS alone.
  bool pos_only = true;             // No registration succeeded: placed from POS (flagged).
  std::vector<int64_t> neighbours;  // Frames it registered to.
  int inliers = 0;                  // Tie points with its neighbours (inliers).
  double residual_px = 0.0;         // RMS tie residual on the mosaic after the last solve.
  double gain = 1.0;                // Radiometric compensation: value' = gain * value + offset.
  double offset = 0.0;
  int optimized_times = 0;  // How many window solves refined it.
  std::string note;         // Why pos_only, or other warnings.
};

// One registered pair, in undistorted image pixels of both frames.
struct PairMatch {
  bool ok = false;
  std::string reason;
  Eigen::Matrix3d base_from_template = Eigen::Matrix3d::Identity();  // Image px -> image px.
  std::vector<Eigen::Vector2d> base_points;      // Inlier tie points in the base frame.
  std::vector<Eigen::Vector2d> template_points;  // The same points in the template frame.
  double residual_rms_px = 0.0;
  // Accuracy (1 sigma, px) of each tie point as the optimizer should weigh it; 0: the
  // FusionOptions::tie_sigma_px default.
  double tie_sigma_px = 0.0;
};

// A frame as the fusion holds it while it can still be a neighbour or be re-rendered.
struct FusionFrame {
  int64_t index = -1;
  double time_s = 0.0;
  cv::Mat image;  // As recorded (CV_8U, CV_16U or CV_32F).
  Eigen::Matrix3d pos_mosaic_from_image = Eigen::Matrix3d::Identity();
  OrthoImage pos_ortho;  // The frame orthorectified by its POS homography.
  // The part of the frame to paint (FrameGeometry::image_clip); empty: all of it.
  std::vector<Eigen::Vector2d> image_clip;
  // Square-root information of the POS placement of the corners and centre (see
  // PosPriorSqrtInformation); zero: isotropic FusionOptions::pos_sigma_px.
  Eigen::Matrix<double, 10, 10> prior_sqrt_information = Eigen::Matrix<double, 10, 10>::Zero();
};

// Registers template against base (both orthorectified by POS). The fusion supplies the
// predicted offset and search radius implicitly through the orthoimages' origins.
using PairRegisterFn = std::function<PairMatch(const FusionFrame& base, const FusionFrame& templ)>;

// Receives the mosaic as it forms. Called from the foreground and from the optimizer's
// re-rendering; implementations must be thread-safe.
class IRMOSAIC_EXPORT MosaicSink {
 public:
  virtual ~MosaicSink() = default;
  // Blends `image` (the frame's pixel type, gain applied) with weight CV_32F in [0, 1] at
  // mosaic pixel `origin_px`: out = w * image + (1 - w) * existing.
  virtual void Paint(const cv::Mat& image, const cv::Mat& weight, cv::Point origin_px) = 0;
  // The same for a frame painted before, again at a refined placement or radiometry (the
  // optimizer's re-renders): a sink may publish it after new frames. Default: Paint.
  virtual void Repaint(const cv::Mat& image, const cv::Mat& weight, cv::Point origin_px) {
    Paint(image, weight, origin_px);
  }
  // A frame was placed or moved.
  virtual void FramePlaced(const FramePlacement& placement) = 0;
  // How far the output is behind what was painted, seconds (0: keeping up): background
  // re-renders pause above FusionOptions::max_output_backlog_s so that they do not delay the
  // publication of new frames. Called from the optimizer thread.
  virtual double OutputBacklogSeconds() const { return 0.0; }
};

struct FusionOptions {
  int window_frames = 300;  // Sliding window of the global optimization.
  // Registration candidates of a new frame: the newest this many frames (0: window_frames).
  // Only they and the frames a solve may still re-render keep their images; older frames
  // stay held without pixels as the frozen ends of pairs (docs/fusion.md, "Held images").
  int candidate_frames = 0;
  // Held images in memory: 0 keeps every held frame's image in memory; N > 0 keeps the newest
  // N there and writes older ones to an unnamed file in spill_directory (system temp folder
  // when empty), read back when a solve re-renders the frame or a new frame registers to it
  // (docs/fusion.md, "Held images"). Where the file cannot be written (disk full), images
  // stay in memory (FusionStats::spill_error).
  int images_in_memory = 0;
  std::string spill_directory;
  int solve_every_frames = 8;  // A window solve starts after this many new frames.
  // Background solves refine only the newest short_window_frames frames of the window (the
  // older ones hold still and anchor them, as frames past the window do), except one in
  // full_window_every, which refines the whole window, as the final solve does. 0: every solve
  // refines the whole window. The older frames have converged, so the placements hardly change
  // (ideal registrar, 2000 frames: mean 0.80 -> 0.79 px; a simulated flight end to end, 1000
  // frames: 1.334 -> 1.346 px), for 68 % less CPU per solve with the ideal registrar (227 -> 72 ms;
  // 41 % end to end), which goes to keeping the mosaic on disk up with the solution and to new
  // frames (docs/benchmarks.md, "Session 17").
  int short_window_frames = 100;
  int full_window_every = 4;
  // Levenberg-Marquardt iterations per stage of a background solve (a plain least-squares
  // stage, then one under the robust losses); the final solve takes 20 per stage over 4
  // stages. Each solve starts where the last one left its frames and solves come every few
  // frames, so 3 reach the placements 6 did (ideal registrar, 2000 frames, 3 seeds: mean
  // 0.798 / 0.913 / 0.883 px with 6, 0.789 / 0.906 / 0.873 with 3) for 35-40 % less CPU per
  // solve; 2 lost accuracy in one seed (docs/fusion.md, "Iterations per solve").
  int solve_iterations = 3;
  // The optimizer thread's nice increment (0..19; 0: the caller's priority). Above 0 its solves
  // and re-renders take the CPU that placing new frames (the caller) and the store's writer
  // (nice 5) leave, instead of an equal share: at 25 fps on 2 cores new frames reach the disk
  // sooner (docs/benchmarks.md, "Session 16"). 0 by default: at 10 the solves start later and
  // less regularly, and a run resumed after kill -9 then differed from an uninterrupted one by
  // up to 1.5 px in 2 of ~60 kills of the fault campaign (bound 0.5 px; docs/fusion.md,
  // "Priorities").
  int optimizer_nice = 0;
  int max_neighbours = 2;  // Registrations per new frame (previous + best other).
  // Pairs of a new frame registered at once, on that many threads (the caller's and helpers);
  // above 1 the registrar is called concurrently and must be thread-safe. The results and
  // their order are the same for any value.
  int registration_threads = 1;
  int max_ties_per_pair = 24;           // Tie points kept per pair for the optimizer.
  double min_overlap_fraction = 0.08;   // Of the smaller footprint, to try a pair.
  double pos_sigma_px = 6.0;            // POS placement accuracy (1 sigma, px) for frames that
                                        // bring no prior_sqrt_information.
  double tie_sigma_px = 0.3;            // Tie point accuracy (1 sigma, px).
  double robust_scale = 3.0;            // Cauchy loss scale, in sigmas of the tie residual.
  double pair_robust_scale_px = 0.5;    // A pair whose mean tie residual is this far off gets
                                        // half weight (a whole pair wrong by a few px).
  double rerender_threshold_px = 0.25;  // Re-render a frame that moved more than this.
  // Re-renders per background solve, the frames that moved most since they were painted
  // first (0: no limit); the final solve re-renders every frame that moved. Bounds the
  // painting and tile writing a solve causes (each re-render rewrites a few tiles).
  int max_rerenders_per_solve = 16;
  // A background solve stops re-rendering (the rest wait for the next solve) while the sink's
  // output is more than this many seconds behind (MosaicSink::OutputBacklogSeconds): new
  // frames reach the disk first, and the re-renders take what the writer can absorb besides.
  // 0: no such pause.
  double max_output_backlog_s = 0.25;
  // Frames no solve refines any more (older than the newest window_frames) whose paint lags
  // their final placement by more than settled_rerender_threshold_px (or their gain or offset
  // by 1 %) are re-rendered: by later solves, before the frames that moved, within the same
  // max_rerenders_per_solve, oldest first, and only while the output is less than half
  // max_output_backlog_s behind; their images are held until then (up to the 2 x
  // window_frames frames held). One still lagging when it leaves the held frames is
  // re-rendered then by Push (on the caller's thread), and the final solve re-renders those
  // still held: every frame ends on disk at its final placement. Without it the disk keeps for
  // good what budgets and pauses left behind. Off by default (a live feed): it costs frame
  // rate and, at 25 fps on 2 cores, publish latency; `irmosaic run` turns it on for recorded
  // flights (docs/fusion.md, "The mosaic on disk", with figures).
  bool rerender_settled_frames = false;
  // The move (largest corner, px) past which a settled frame is re-rendered; its gain and
  // offset as for the others.
  double settled_rerender_threshold_px = 0.25;
  bool optimize = true;           // Run the global optimization thread.
  bool compensate_gain = true;    // Per-frame gain and offset from the overlaps.
  double gain_prior_sigma = 0.5;  // Keeps the global level: gain ~ 1 +- this.
  int feather_px = 24;            // Seam blending ramp width.
  int tie_patch_radius_px = 3;    // Radiometric samples: mean of a (2r+1)^2 patch.
  bool render = true;             // Paint into the sink (off for geometry-only runs).
  // Ceres linear solver and sparse library by their Ceres names (docs/fusion.md, "Sparse
  // solver", has the measured choice: Eigen's sparse Cholesky, single-threaded, costs a window
  // less CPU than SuiteSparse's CHOLMOD, whose OpenMP workers spin beside the optimizer).
  std::string linear_solver = "SPARSE_NORMAL_CHOLESKY";
  std::string sparse_library = "EIGEN_SPARSE";
  // At Finish(), the covariance of the last solve (Ceres) gives the expected placement RMSE
  // of its frames under the tie and POS error models: FusionStats::predicted_rmse_px.
  bool estimate_precision = false;

  // Returns false and a message when an option is out of range.
  bool IsValid(std::string* error) const;
};

// Figures a user can print.
struct FusionStats {
  int64_t frames = 0;
  int64_t frames_registered = 0;
  int64_t frames_pos_only = 0;
  int64_t pairs_tried = 0;
  int64_t pairs_ok = 0;
  int64_t solves = 0;
  int64_t full_solves = 0;  // Of them, those that refined the whole window (short_window_frames).
  int64_t rerendered_frames = 0;
  // Of them, the final solve's (Finish) whose orthoimage a registration helper thread made
  // while the frame before was painted (registration_threads > 1).
  int64_t rerendered_ahead = 0;
  // Re-renders a background solve chose but left to the next one because the output was
  // behind (FusionOptions::max_output_backlog_s).
  int64_t deferred_rerenders = 0;
  // Frames solves found to need a re-render (counted at each solve that finds them: rendered,
  // deferred or over the budget), and of them those for their gain or offset alone (moved less
  // than rerender_threshold_px).
  int64_t rerender_candidates = 0;
  int64_t radiometric_rerenders = 0;
  // Settled frames (older than the newest window_frames: no solve moves them again) whose
  // paint lagged their placement: found by solves (counted at each solve that finds them),
  // re-rendered (by solves or as they left the held frames), of those the ones re-rendered as
  // they left, and the ones that left without (their image could not be read back; the disk
  // keeps them where they were last painted).
  int64_t settled_rerender_candidates = 0;
  int64_t settled_rerenders = 0;
  int64_t settled_rerenders_on_leaving = 0;
  int64_t settled_left_lagging = 0;
  // Of the re-renders as frames left, those painted again because a solve that still held the
  // frame moved it while the first paint ran.
  int64_t settled_repainted_after_solve = 0;
  // What the mosaic on disk lags behind the placements after each background solve's
  // re-renders, averaged over the solves (mosaic px): the RMS over the window's pairs of the
  // seam lag (the base frame's move since painted less the template's, at the overlap), and
  // the RMS over the window's frames of their move since painted (largest corner).
  double mean_seam_lag_px = 0.0;
  double mean_painted_lag_px = 0.0;
  double last_solve_ms = 0.0;
  double max_solve_ms = 0.0;
  double total_solve_ms = 0.0;
  double max_solve_cpu_ms = 0.0;     // The solving thread's CPU time (a loaded machine inflates
  double total_solve_cpu_ms = 0.0;   // wall time, not this).
  int64_t optimizer_lag_frames = 0;  // Frames pushed but not yet in a finished solve.
  int64_t held_frames = 0;           // Frames held (placements, footprints, ends of pairs).
  int64_t placements_held = 0;       // Placements in memory (all but the released ones).
  int64_t held_images = 0;           // Of those, frames that still hold their image,
  int64_t held_image_bytes = 0;      // and the bytes of those images (summed per frame).
  int64_t spilled_images = 0;        // Held images on disk now (FusionOptions::images_in_memory),
  int64_t spill_file_bytes = 0;      // the size the file has grown to,
  int64_t spill_reads = 0;           // and the images read back from it so far.
  std::string spill_error;           // The first failure to write or read it, or empty.
  // Root mean of the predicted squared placement error (5x5 grid of each frame, mosaic px)
  // over the frames of the final solve; 0 unless FusionOptions::estimate_precision.
  double predicted_rmse_px = 0.0;
};

// The fusion state a resumed run starts from, as a published moment recorded it
// (MapFusion::ResumeState, MapFusion::Resume): every frame's placement, which frames were still
// held, the optimizer's pair weights and where its solves stood. Frames that had left the held
// window stay exactly where they were published; the held ones are replayed (their images
// pushed again) so the optimizer continues as the uninterrupted run would have.
struct FusionResumeState {
  // A pair the optimizer still used, by frame index, in registration order.
  struct Pair {
    int64_t base = -1;
    int64_t templ = -1;
    double weight = 1.0;  // Its pair-level weight (docs/fusion.md, "Pair weights").
  };
  std::vector<FramePlacement> placements;  // In push order, from slot `first_slot` on.
  size_t first_slot = 0;                   // Push-order position of placements.front().
  // Frames before first_slot (not in `placements`; Resume with first_slot > 0): how many were
  // registered and how many placed from POS alone, for FusionStats. ResumeState sets 0.
  int64_t released_registered = 0;
  int64_t released_pos_only = 0;
  size_t frozen_slots = 0;         // Frames before this push-order position never change again.
  int64_t held_from = -1;          // Index of the oldest frame held (-1: none).
  std::vector<Pair> pairs;         // Pairs still in use (each one's template frame is held).
  int64_t frames_since_solve = 0;  // Frames pushed since the last solve took its snapshot.
  int64_t solving_through = -1;    // Newest frame of a solve running at that moment, or -1.
  // Held frames last painted elsewhere than at their placement in `placements` (a re-render
  // not yet done): where. A resumed run takes a replayed frame as painted there, so one whose
  // paint lagged at the record is still re-rendered (settled re-renders; docs/fusion.md).
  struct Painted {
    int64_t index = -1;
    Eigen::Matrix3d mosaic_from_image = Eigen::Matrix3d::Identity();
    double gain = 1.0;
    double offset = 0.0;
  };
  std::vector<Painted> painted;

  // Oldest frame a replay must push again: held_from, or an older base of a pair in use
  // (-1: nothing to replay).
  int64_t ReplayFrom() const;
};

// Map fusion (paper section 5): a real-time mapping step in the caller's thread and a global
// optimization thread over a sliding window (Ceres), with radiometric compensation and
// feathered seams. Push() never waits for the optimizer.
//
// Thread-safety: Push(), Resume() and Finish() from one thread; Placements(), ResumeState() and
// stats() from any.
class IRMOSAIC_EXPORT MapFusion {
 public:
  // Does NOT take ownership of `sink`, which must outlive this object (may be null).
  MapFusion(FusionOptions options, CameraModel camera, PairRegisterFn registrar, MosaicSink* sink);
  ~MapFusion();
  MapFusion(const MapFusion&) = delete;
  MapFusion& operator=(const MapFusion&) = delete;

  // Places a frame now: registers it to its neighbours, maps it through the best neighbour's
  // latest homography (or POS when none registered) and renders it. Returns its placement.
  FramePlacement Push(FusionFrame frame);

  // Runs a last solve over the window, re-renders what moved and stops the thread.
  void Finish();

  // Latest placement of every frame pushed so far (and of every frame given to Resume), from
  // the first one not released (ReleasePlacements) on, in push order.
  std::vector<FramePlacement> Placements() const;

  // Drops the placements before push-order position `before_slot` that can never change or be
  // read again (frozen: older than the window, than the bases of its pairs, than the frames and
  // pairs of a solve that has not returned, re-renders included, or of a replay), for a caller that
  // keeps them itself (the Mosaicker's frozen frames' file), so that memory does not grow with the
  // flight. Returns the first slot still held (the new start of Placements()).
  size_t ReleasePlacements(size_t before_slot);

  // A consistent snapshot of the state a resumed run needs, with the placements from push-order
  // position `from_slot` on (a caller that kept the frozen ones asks for the rest only).
  FusionResumeState ResumeState(size_t from_slot = 0) const;
  // Starts from a recorded state instead of empty, before the first Push: its placements
  // become the placements of those frames (from first_slot on: the older ones count as
  // released, and must be frozen; the state must hold every frame from ReplayFrom() on). The frames
  // from state.ReplayFrom() to the last recorded one must then be pushed again, in order, as
  // before: each is re-registered to the neighbours the record names and keeps its recorded
  // placement (nothing is rendered or solved). The first newer frame (or Finish) ends the
  // replay: frames older than held_from leave the window, a solve that was running at the
  // record is run again, and the optimizer goes on. Frames older than ReplayFrom() are never
  // pushed again: they stay frozen at their recorded placement. Throws std::invalid_argument after
  // a Push, for duplicate indices, or later from Push for a replayed frame the record does not
  // hold.
  void Resume(FusionResumeState state);
  FusionStats stats() const;

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace irmosaic
