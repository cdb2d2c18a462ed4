#include "irmosaic/map_fusion.h"

#include <ceres/ceres.h>
#include <pthread.h>
#include <time.h>

#include <Eigen/Dense>
#include <Eigen/Sparse>
#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <deque>
#include <exception>
#include <filesystem>
#include <limits>
#include <map>
#include <mutex>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <set>
#include <stdexcept>
#include <thread>

#include "buffer_view.h"
#include "feather_weight.h"
#include "fusion_cost.h"
#include "helper_threads.h"
#include "image_spill.h"
#include "irmosaic/frame_geometry.h"
#include "map_fusion_testing.h"
#include "thread_priority.h"

namespace irmosaic {
namespace fusion_testing {
namespace {
std::atomic<SolveSnapshotHook> g_solve_snapshot_hook{nullptr};
std::atomic<SettledPaintHook> g_settled_paint_hook{nullptr};
}  // namespace
void SetSolveSnapshotHook(SolveSnapshotHook hook) { g_solve_snapshot_hook.store(hook); }
void SetSettledPaintHook(SettledPaintHook hook) { g_settled_paint_hook.store(hook); }
}  // namespace fusion_testing
namespace {

using Clock = std::chrono::steady_clock;

// CPU time of the calling thread, ms.
double ThreadCpuMs() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) * 1e3 + static_cast<double>(ts.tv_nsec) * 1e-6;
}

using fusion::ApplyDelta;
using fusion::Normalizer;
using fusion::PairTieCost;
using fusion::PriorCost;
using fusion::TieLoss;

// Mean of a small patch around an undistorted point (for radiometric ties); NaN if outside.
double PatchMean(const cv::Mat& image, const CameraModel& camera, const Eigen::Vector2d& p,
                 int radius) {
  const Eigen::Vector2d raw = camera.Distort(p);
  const int x = static_cast<int>(std::lround(raw.x())), y = static_cast<int>(std::lround(raw.y()));
  if (x - radius < 0 || y - radius < 0 || x + radius >= image.cols || y + radius >= image.rows) {
    return std::numeric_limits<double>::quiet_NaN();
  }
  return cv::mean(image(cv::Rect(x - radius, y - radius, 2 * radius + 1, 2 * radius + 1)))[0];
}

std::vector<cv::Point2f> Footprint(const Eigen::Matrix3d& h, const CameraModel& camera) {
  std::vector<cv::Point2f> quad;
  for (const Eigen::Vector2d& c :
       {Eigen::Vector2d(-0.5, -0.5), Eigen::Vector2d(camera.width - 0.5, -0.5),
        Eigen::Vector2d(camera.width - 0.5, camera.height - 0.5),
        Eigen::Vector2d(-0.5, camera.height - 0.5)}) {
    const Eigen::Vector2d q = ApplyHomography(h, c);
    quad.emplace_back(static_cast<float>(q.x()), static_cast<float>(q.y()));
  }
  return quad;
}

// Largest displacement of the image corners between two placements, mosaic pixels.
double CornerShift(const Eigen::Matrix3d& a, const Eigen::Matrix3d& b, const CameraModel& camera) {
  const auto qa = Footprint(a, camera), qb = Footprint(b, camera);
  double worst = 0.0;
  for (int k = 0; k < 4; ++k) worst = std::max<double>(worst, cv::norm(qa[k] - qb[k]));
  return worst;
}

}  // namespace

bool FusionOptions::IsValid(std::string* error) const {
  auto fail = [&](const std::string& text) {
    if (error) *error = text;
    return false;
  };
  if (window_frames < 2) return fail("window_frames must be at least 2");
  if (candidate_frames < 0) return fail("candidate_frames must be >= 0 (0: window_frames)");
  if (images_in_memory < 0) return fail("images_in_memory must be >= 0 (0: all)");
  if (solve_every_frames < 1) return fail("solve_every_frames must be at least 1");
  if (short_window_frames < 0) return fail("short_window_frames must be >= 0 (0: off)");
  if (full_window_every < 1) return fail("full_window_every must be at least 1");
  if (solve_iterations < 1) return fail("solve_iterations must be at least 1");
  if (optimizer_nice < 0 || optimizer_nice > 19) {
    return fail("optimizer_nice must be in 0..19");
  }
  if (max_neighbours < 1) return fail("max_neighbours must be at least 1");
  if (registration_threads < 1 || registration_threads > 64) {
    return fail("registration_threads must be in 1..64");
  }
  if (!(min_overlap_fraction > 0.0 && min_overlap_fraction < 1.0))
    return fail("min_overlap_fraction must be in (0, 1)");
  if (!(pos_sigma_px > 0.0)) return fail("pos_sigma_px must be positive");
  if (!(tie_sigma_px > 0.0)) return fail("tie_sigma_px must be positive");
  if (!(robust_scale > 0.0)) return fail("robust_scale must be positive");
  if (!(pair_robust_scale_px > 0.0)) return fail("pair_robust_scale_px must be positive");
  if (!(rerender_threshold_px >= 0.0)) return fail("rerender_threshold_px must be >= 0");
  if (!(settled_rerender_threshold_px >= 0.0)) {
    return fail("settled_rerender_threshold_px must be >= 0");
  }
  if (!(gain_prior_sigma > 0.0)) return fail("gain_prior_sigma must be positive");
  if (feather_px < 1) return fail("feather_px must be at least 1");
  if (max_rerenders_per_solve < 0) return fail("max_rerenders_per_solve must be >= 0");
  if (!(max_output_backlog_s >= 0.0)) return fail("max_output_backlog_s must be >= 0");
  ceres::LinearSolverType solver_type;
  if (!ceres::StringToLinearSolverType(linear_solver, &solver_type) ||
      solver_type == ceres::DENSE_SCHUR || solver_type == ceres::SPARSE_SCHUR ||
      solver_type == ceres::ITERATIVE_SCHUR) {
    return fail(
        "linear_solver must be a Ceres linear solver without Schur elimination "
        "(e.g. SPARSE_NORMAL_CHOLESKY, DENSE_QR, CGNR), not '" +
        linear_solver + "'");
  }
  ceres::SparseLinearAlgebraLibraryType library;
  if (!ceres::StringToSparseLinearAlgebraLibraryType(sparse_library, &library)) {
    return fail("sparse_library must be SUITE_SPARSE, CX_SPARSE or EIGEN_SPARSE, not '" +
                sparse_library + "'");
  }
  if (solver_type == ceres::SPARSE_NORMAL_CHOLESKY &&
      !ceres::IsSparseLinearAlgebraLibraryTypeAvailable(library)) {
    return fail("sparse_library " + sparse_library +
                " is not in this build of Ceres; choose one it has (SUITE_SPARSE, EIGEN_SPARSE) "
                "or a dense linear_solver (DENSE_QR)");
  }
  return true;
}

class MapFusion::Impl {
  struct Renderer;  // Below: an orthorectifier and a weight buffer per painting thread.

 public:
  Impl(FusionOptions options, CameraModel camera, PairRegisterFn registrar, MosaicSink* sink)
      : options_(options),
        camera_(std::move(camera)),
        registrar_(std::move(registrar)),
        sink_(sink),
        foreground_(camera_),
        background_(camera_) {
    std::string error;
    if (!options_.IsValid(&error)) throw std::invalid_argument("FusionOptions: " + error);
    normalizer_ = {(camera_.width - 1) / 2.0, (camera_.height - 1) / 2.0,
                   std::max(camera_.width, camera_.height) / 2.0};
    if (options_.images_in_memory > 0) {
      std::string directory = options_.spill_directory;
      if (directory.empty()) {
        std::error_code ignored;
        directory = std::filesystem::temp_directory_path(ignored).string();
      }
      spill_ = std::make_unique<ImageSpill>(directory);
    }
    if (options_.registration_threads > 1) {
      registration_helpers_ = std::make_unique<HelperThreads>(
          static_cast<size_t>(options_.registration_threads - 1), "irm-register");
    }
    if (options_.optimize) optimizer_ = std::thread([this] { OptimizerLoop(); });
  }

  ~Impl() { StopThread(); }

  FramePlacement Push(FusionFrame input) {
    auto frame = std::make_shared<Held>();
    frame->data = std::move(input);
    frame->pos_footprint = Footprint(frame->data.pos_mosaic_from_image, camera_);
    frame->prior_sqrt_information =
        frame->data.prior_sqrt_information.isZero()
            ? Eigen::Matrix<double, 10, 10>(Eigen::Matrix<double, 10, 10>::Identity() /
                                            options_.pos_sigma_px)
            : frame->data.prior_sqrt_information;
    if (replaying_) {
      if (frame->data.index <= replay_last_) return ReplayPush(frame);
      EndReplay();
    }
    FramePlacement placement;
    placement.index = frame->data.index;
    placement.time_s = frame->data.time_s;
    placement.pos_mosaic_from_image = frame->data.pos_mosaic_from_image;
    placement.mosaic_from_image = frame->data.pos_mosaic_from_image;

    // Neighbours by POS footprint overlap among the newest candidate_frames, the most recent
    // frame first (the older held frames have no image; the count alone decides, so a resumed
    // run sees the same candidates).
    std::vector<std::shared_ptr<Held>> candidates;
    {
      std::lock_guard<std::mutex> lock(mu_);
      const size_t count = std::min(CandidateCount(), window_.size());
      candidates.assign(window_.rbegin(), window_.rbegin() + static_cast<std::ptrdiff_t>(count));
    }
    std::vector<std::pair<double, std::shared_ptr<Held>>> scored;
    const double own_area = cv::contourArea(frame->pos_footprint);
    for (size_t k = 0; k < candidates.size(); ++k) {
      std::vector<cv::Point2f> overlap;
      const float area = cv::intersectConvexConvex(candidates[k]->pos_footprint,
                                                   frame->pos_footprint, overlap, true);
      const double fraction =
          area / std::min(own_area, cv::contourArea(candidates[k]->pos_footprint));
      if (fraction >= options_.min_overlap_fraction) {
        // The previous frame of the sweep goes first whatever its overlap.
        scored.emplace_back(k == 0 ? 2.0 : fraction, candidates[k]);
      }
    }
    std::stable_sort(scored.begin(), scored.end(),
                     [](const auto& a, const auto& b) { return a.first > b.first; });
    if (static_cast<int>(scored.size()) > options_.max_neighbours) {
      scored.resize(options_.max_neighbours);
    }

    // Register, and collect template points with their mosaic positions through each
    // neighbour's latest placement.
    std::vector<Eigen::Vector2d> template_pts, mosaic_pts;
    std::vector<std::pair<double, double>> radiometric;  // (value in new frame, target value).
    std::vector<Pair> new_pairs;
    // Neighbours whose image is on disk (images_in_memory) are read back for the pair.
    std::vector<cv::Mat> base_images(scored.size());
    for (size_t k = 0; k < scored.size(); ++k) base_images[k] = ImageOf(*scored[k].second);
    std::vector<PairMatch> matches = RegisterPairs(scored, base_images, frame->data);
    for (size_t k = 0; k < scored.size(); ++k) {
      const std::shared_ptr<Held>& neighbour = scored[k].second;
      PairMatch match = std::move(matches[k]);
      ++pairs_tried_;
      if (!match.ok) {
        placement.note += "pair with " + std::to_string(neighbour->data.index) +
                          " failed: " + match.reason + "; ";
        continue;
      }
      ++pairs_ok_;
      Pair pair = MakePair(neighbour, base_images[k], frame, std::move(match));
      Eigen::Matrix3d h_base;
      double gain_base = 1.0, offset_base = 0.0;
      {
        std::lock_guard<std::mutex> lock(mu_);
        h_base = PlacementAt(neighbour->slot).mosaic_from_image;
        gain_base = PlacementAt(neighbour->slot).gain;
        offset_base = PlacementAt(neighbour->slot).offset;
      }
      for (size_t t = 0; t < pair.base_points.size(); ++t) {
        template_pts.push_back(pair.template_points[t]);
        mosaic_pts.push_back(ApplyHomography(h_base, pair.base_points[t]));
        const double vb = pair.base_values[t], vt = pair.template_values[t];
        if (std::isfinite(vb) && std::isfinite(vt)) {
          radiometric.emplace_back(vt, gain_base * vb + offset_base);
        }
      }
      placement.neighbours.push_back(neighbour->data.index);
      placement.inliers += static_cast<int>(pair.base_points.size());
      new_pairs.push_back(std::move(pair));
    }
    // Real-time mapping: the neighbours' latest homographies place the tie points on the
    // mosaic (H_i * H(j->i)); the mean shift from the POS placement onto them corrects
    // H_pos_j. Rotation or scale fitted on a 10-40 % overlap strip extrapolates across the
    // frame with a gain above one, so chaining them diverges exponentially (measured in
    // map_fusion_test); a translation cannot. POS keeps the shape; the optimizer refines it.
    if (template_pts.size() >= 4) {
      std::vector<Eigen::Vector2d> from;
      for (const Eigen::Vector2d& t : template_pts) {
        from.push_back(ApplyHomography(frame->data.pos_mosaic_from_image, t));
      }
      Eigen::Matrix3d correction = Eigen::Matrix3d::Identity();
      for (size_t t = 0; t < from.size(); ++t) {
        correction.block<2, 1>(0, 2) +=
            (mosaic_pts[t] - from[t]) / static_cast<double>(from.size());
      }
      placement.mosaic_from_image = correction * frame->data.pos_mosaic_from_image;
      placement.mosaic_from_image /= placement.mosaic_from_image(2, 2);
      placement.pos_only = false;
      double sum_sq = 0.0;
      for (size_t t = 0; t < template_pts.size(); ++t) {
        sum_sq += (ApplyHomography(placement.mosaic_from_image, template_pts[t]) - mosaic_pts[t])
                      .squaredNorm();
      }
      placement.residual_px = std::sqrt(sum_sq / static_cast<double>(template_pts.size()));
    } else if (scored.empty()) {
      placement.note += "no overlapping neighbour; ";
    }
    if (options_.compensate_gain) FitGain(radiometric, &placement.gain, &placement.offset);

    std::vector<Due> due;  // Settled frames leaving the fusion with their paint lagging.
    {
      std::lock_guard<std::mutex> lock(mu_);
      frame->slot = base_slot_ + placements_.size();
      frame->rendered = placement;
      placements_.push_back(placement);
      window_.push_back(frame);
      for (Pair& p : new_pairs) pairs_.push_back(std::move(p));
      ++frames_since_solve_;
      if (placement.pos_only) {
        ++frames_pos_only_;
      } else {
        ++frames_registered_;
      }
      // Frames leaving the window are frozen; pairs with no frame in the window are dropped.
      // While the optimizer runs behind (a loaded machine), frames it has not refined yet are
      // held up to kMaxHeldWindows windows, so they are refined late rather than frozen with
      // their chained placement; past that they are frozen, with a note.
      const size_t keep = 2 * static_cast<size_t>(options_.window_frames);
      const size_t hard = kMaxHeldWindows * static_cast<size_t>(options_.window_frames);
      while (window_.size() > keep) {
        FramePlacement& oldest_placement = PlacementAt(window_.front()->slot);
        const bool unrefined = options_.optimize && oldest_placement.optimized_times == 0;
        if (unrefined && window_.size() <= hard) break;
        if (unrefined) oldest_placement.note += "frozen unrefined (optimizer behind); ";
        Held& leaving = *window_.front();
        leaving.left_fusion = true;
        if (PaintLagsFinal(leaving)) {
          // Its last chance: re-rendered here, after the lock, before this Push returns (so a
          // resume record that counts it as frozen finds it painted). A solve that picked it
          // passes it over from now on; one already painting it paints the same placement.
          due.push_back(
              {window_.front(), oldest_placement, ImageRef{leaving.data.image, leaving.spilled}});
        }
        window_.pop_front();
      }
      const int64_t oldest = window_.front()->data.index;
      while (!pairs_.empty() && pairs_.front().base->data.index < oldest &&
             pairs_.front().templ->data.index < oldest) {
        pairs_.pop_front();
      }
      ReleaseImagesLocked();
    }
    Render(frame->data.image, frame->data.image_clip, placement, &foreground_);
    if (sink_) sink_->FramePlaced(placement);
    {
      // From now on a solve may re-render it (one that finished before this paint would have
      // been overwritten by it, and the frame's `rendered` would not say so).
      std::lock_guard<std::mutex> lock(mu_);
      frame->painted = true;
    }
    if (options_.optimize) cv_.notify_one();
    for (const Due& d : due) RenderSettled(d.frame, d.placement, d.image, &foreground_);
    SpillImages();
    return placement;
  }

  void Finish() {
    EndReplay();
    StopThread();
    if (options_.optimize) SolveWindow(true);
  }

  std::vector<FramePlacement> Placements() const {
    std::lock_guard<std::mutex> lock(mu_);
    return {placements_.begin(), placements_.end()};
  }

  size_t ReleasePlacements(size_t before_slot) {
    std::lock_guard<std::mutex> lock(mu_);
    // Never a placement something may still read or change: the window's, the bases of its
    // pairs, a running solve's snapshot and a replay's.
    size_t limit = std::min(before_slot, base_slot_ + placements_.size());
    if (!window_.empty()) limit = std::min(limit, window_.front()->slot);
    for (const Pair& p : pairs_) limit = std::min(limit, p.base->slot);
    if (solving_) limit = std::min(limit, solving_min_slot_);
    limit = std::min(limit, solve_reads_from_);
    if (replaying_) limit = std::min(limit, resume_.frozen_slots);
    while (base_slot_ < limit) {
      placements_.pop_front();
      ++base_slot_;
    }
    return base_slot_;
  }

  FusionResumeState ResumeState(size_t from_slot) const {
    std::lock_guard<std::mutex> lock(mu_);
    FusionResumeState state;
    if (replaying_) {
      // Nothing has moved since the record this run resumed from: hand it on unchanged.
      state = resume_;
    } else {
      state.held_from = window_.empty() ? -1 : window_.front()->data.index;
      for (const Pair& p : pairs_) {
        state.pairs.push_back({p.base->data.index, p.templ->data.index, *p.weight});
      }
      state.frames_since_solve = frames_since_solve_;
      state.solving_through = solving_ ? PlacementAt(solving_last_slot_).index : -1;
      for (const auto& f : window_) {
        const FramePlacement& live = PlacementAt(f->slot);
        if (f->rendered.mosaic_from_image != live.mosaic_from_image ||
            f->rendered.gain != live.gain || f->rendered.offset != live.offset) {
          state.painted.push_back(
              {f->data.index, f->rendered.mosaic_from_image, f->rendered.gain, f->rendered.offset});
        }
      }
      // Frames that left the window never move again, unless a running solve still holds them
      // (the foreground got more than a window ahead of it).
      state.frozen_slots =
          window_.empty() ? base_slot_ + placements_.size() : window_.front()->slot;
      if (solving_) state.frozen_slots = std::min(state.frozen_slots, solving_first_slot_);
    }
    state.first_slot = std::clamp(from_slot, base_slot_, base_slot_ + placements_.size());
    state.placements.assign(
        placements_.begin() + static_cast<std::ptrdiff_t>(state.first_slot - base_slot_),
        placements_.end());
    state.released_registered = state.released_pos_only = 0;
    return state;
  }

  void Resume(FusionResumeState state) {
    std::lock_guard<std::mutex> lock(mu_);
    if (!placements_.empty() || replaying_) {
      throw std::invalid_argument("MapFusion::Resume: call it before the first Push");
    }
    const int64_t replay_from = state.ReplayFrom();
    if (state.first_slot != 0 && !state.placements.empty() && replay_from >= 0 &&
        state.placements.front().index > replay_from) {
      throw std::invalid_argument("MapFusion::Resume: the state must hold the placements from " +
                                  std::to_string(replay_from) + " (the replay's first frame) on");
    }
    std::set<int64_t> seen;
    for (size_t k = 0; k < state.placements.size(); ++k) {
      const size_t slot = state.first_slot + k;
      FramePlacement& p = state.placements[k];
      if (!seen.insert(p.index).second) {
        throw std::invalid_argument("MapFusion::Resume: frame " + std::to_string(p.index) +
                                    " is recorded twice");
      }
      if (replay_from >= 0 && p.index >= replay_from) replay_slots_[p.index] = slot;
      replay_last_ = std::max(replay_last_, p.index);
      ++(p.pos_only ? frames_pos_only_ : frames_registered_);
    }
    frames_registered_ += state.released_registered;
    frames_pos_only_ += state.released_pos_only;
    base_slot_ = state.first_slot;
    for (const FusionResumeState::Pair& p : state.pairs) replay_pairs_.emplace(p.templ, p);
    placements_.assign(std::make_move_iterator(state.placements.begin()),
                       std::make_move_iterator(state.placements.end()));
    state.placements.clear();
    state.frozen_slots = base_slot_ + placements_.size();
    for (const auto& [index, slot] : replay_slots_) {
      state.frozen_slots = std::min(state.frozen_slots, slot);
    }
    resume_ = std::move(state);
    replaying_ = !replay_slots_.empty();
  }

  FusionStats stats() const {
    std::lock_guard<std::mutex> lock(mu_);
    FusionStats s = stats_;
    s.frames = static_cast<int64_t>(base_slot_ + placements_.size());
    s.placements_held = static_cast<int64_t>(placements_.size());
    s.frames_registered = frames_registered_;
    s.frames_pos_only = frames_pos_only_;
    s.pairs_tried = pairs_tried_;
    s.pairs_ok = pairs_ok_;
    s.optimizer_lag_frames = frames_since_solve_;
    s.held_frames = static_cast<int64_t>(window_.size());
    for (const auto& f : window_) {
      if (f->spilled) ++s.spilled_images;
      if (f->data.image.empty()) continue;
      ++s.held_images;
      s.held_image_bytes += static_cast<int64_t>(f->data.image.total() * f->data.image.elemSize());
    }
    if (spill_) {
      s.spill_file_bytes = static_cast<int64_t>(spill_->slots() * spill_->bytes_per_image());
      s.spill_error = spill_->error();
    }
    s.spill_reads = spill_reads_;
    return s;
  }

 private:
  struct Held {
    FusionFrame data;
    Eigen::Matrix<double, 10, 10> prior_sqrt_information;
    size_t slot = 0;
    std::vector<cv::Point2f> pos_footprint;
    FramePlacement rendered;  // As last painted (under mu_): re-renders compare with it.
    // Under mu_: the producer's first paint is done (solves re-render only painted frames);
    // the frame has left the window (the held frames; Push re-rendered it then if its paint
    // lagged, and a solve that still moves it re-renders it whatever its budget).
    bool painted = false;
    bool left_fusion = false;
    // Under mu_: where a solve put the frame after it left the fusion (a solve whose snapshot
    // still held it, running while Push re-rendered it at the placement before): the frame's
    // placement is not read from placements_ then, whose older slots the store may release.
    std::optional<FramePlacement> moved_after_leaving;
    // The image on disk instead of in data.image (images_in_memory); written by the producer
    // under mu_.
    std::shared_ptr<const ImageSpill::Handle> spilled;
  };
  // A frame's image as a solve keeps it for its re-renders: in memory or on disk.
  struct ImageRef {
    cv::Mat image;
    std::shared_ptr<const ImageSpill::Handle> spilled;
  };
  // A settled frame that leaves the fusion with its paint lagging, re-rendered by Push.
  struct Due {
    std::shared_ptr<Held> frame;
    FramePlacement placement;
    ImageRef image;
  };
  struct Pair {
    std::shared_ptr<Held> base, templ;
    std::vector<Eigen::Vector2d> base_points, template_points;
    std::vector<double> base_values, template_values;
    double tie_sigma_px = 0.0;
    // Pair-level weight from its consistency with the rest of the network, carried from one
    // solve to the next. Written by the solver only (one at a time), read by it.
    std::shared_ptr<double> weight = std::make_shared<double>(1.0);
  };

  size_t CandidateCount() const {
    return static_cast<size_t>(options_.candidate_frames > 0 ? options_.candidate_frames
                                                             : options_.window_frames);
  }

  // How far a frame's paint lags `live`, in units of the re-render thresholds (above 1: to be
  // re-rendered): the largest corner move over `threshold_px` (negative: rerender_threshold_px),
  // or the gain or offset change over 1 % (of the offset's scale). `shift` gets the move's part.
  double PaintLag(const FramePlacement& painted, const FramePlacement& live,
                  double* shift = nullptr, double threshold_px = -1.0) const {
    if (threshold_px < 0.0) threshold_px = options_.rerender_threshold_px;
    const double value_scale = std::max(1.0, std::abs(live.offset) + 1000.0);
    const double radiometry =
        std::max(std::abs(live.gain - painted.gain) / 0.01,
                 std::abs(live.offset - painted.offset) / (0.01 * value_scale));
    const double moved = CornerShift(painted.mosaic_from_image, live.mosaic_from_image, camera_) /
                         std::max(threshold_px, 1e-9);
    if (shift) *shift = moved;
    return std::max(moved, radiometry);
  }

  // A refined frame that still holds its image (under mu_) and whose paint lags its
  // placement: a re-render is due once no solve will move it again.
  bool PaintLagsFinal(const Held& f) const {
    if (!options_.render || !options_.optimize || !options_.rerender_settled_frames || replaying_) {
      return false;
    }
    if (f.data.image.empty() && !f.spilled) return false;
    const FramePlacement& live = PlacementAt(f.slot);
    return live.optimized_times > 0 &&
           PaintLag(f.rendered, live, nullptr, options_.settled_rerender_threshold_px) > 1.0;
  }

  // Re-renders a settled frame leaving the fusion at its final placement (Push, after the
  // lock). A frame whose image cannot be read back keeps its lagging paint, counted.
  void RenderSettled(const std::shared_ptr<Held>& frame, const FramePlacement& placement,
                     const ImageRef& ref, Renderer* renderer) {
    const cv::Mat image = ImageOf(ref);
    if (image.empty()) {
      std::lock_guard<std::mutex> lock(mu_);
      stats_.settled_left_lagging += 1;
      return;
    }
    // Painted as new, not as a refresh: its tiles go with the next publish, whose resume record
    // counts the frame as frozen at this placement (a refresh's tiles are written in slices
    // after that publish, and a kill in between left the frozen frame painted elsewhere for
    // good). At the sensor's rate frames leave settled already (docs/fusion.md), so this adds
    // to the publishes only when the writer is saturated.
    // A solve whose snapshot held the frame may publish a newer placement meanwhile: it
    // re-renders the frame there too (forced, SolveWindow), but this paint and its record, if
    // they came last, would leave the frame on disk where the solution no longer puts it
    // (session 43). So the paint is checked after it is done and made again at the newer
    // placement; the solve's record waits on records_mu_ until this one is written.
    FramePlacement painting = placement;
    for (;;) {
      Render(image, frame->data.image_clip, painting, renderer);
      if (const auto hook = fusion_testing::g_settled_paint_hook.load()) hook(frame->data.index);
      std::lock_guard<std::mutex> records(records_mu_);
      {
        std::lock_guard<std::mutex> lock(mu_);
        if (frame->moved_after_leaving &&
            frame->moved_after_leaving->optimized_times != painting.optimized_times) {
          painting = *frame->moved_after_leaving;
          stats_.settled_repainted_after_solve += 1;
          continue;
        }
        frame->rendered = painting;
        stats_.settled_rerenders += 1;
        stats_.settled_rerenders_on_leaving += 1;
      }
      if (sink_) sink_->FramePlaced(painting);
      return;
    }
  }

  // Frees the images of held frames that are no registration candidate any more and that no
  // solve can re-render: older than the newest candidate_frames and window_frames, and
  // refined (a solve reaches back past its window only to unrefined frames), and out of a
  // running solve's frames (it holds their images for its own re-renders only, which its
  // budget may not reach; a frame it moves then is re-rendered later, when its paint lags its
  // final placement). They stay held as frozen ends of pairs. Not during a replay: its
  // interrupted solve may still need them.
  void ReleaseImagesLocked() {
    const size_t count = std::max(CandidateCount(), static_cast<size_t>(options_.window_frames));
    for (size_t k = 0; k + count < window_.size(); ++k) {
      Held& f = *window_[k];
      if (f.data.image.empty() && !f.spilled) continue;
      if (options_.optimize && PlacementAt(f.slot).optimized_times == 0) continue;
      if (PaintLagsFinal(f)) continue;  // A solve re-renders it first (SolveWindow).
      if (solving_ && f.slot >= solving_first_slot_) continue;  // Moved once more (session 43).
      f.data.image.release();
      f.spilled.reset();
    }
  }

  // Moves the images of held frames older than the newest images_in_memory to the spill file
  // (producer thread; the writes run outside mu_). An image the file refuses (disk full) stays
  // in memory.
  void SpillImages() {
    if (!spill_) return;
    std::vector<std::shared_ptr<Held>> older;
    {
      std::lock_guard<std::mutex> lock(mu_);
      const size_t keep = static_cast<size_t>(options_.images_in_memory);
      for (size_t k = 0; k + keep < window_.size(); ++k) {
        if (!window_[k]->data.image.empty() && !window_[k]->spilled) older.push_back(window_[k]);
      }
    }
    for (const std::shared_ptr<Held>& f : older) {
      std::shared_ptr<const ImageSpill::Handle> handle = spill_->Put(f->data.image);
      if (!handle) continue;
      std::lock_guard<std::mutex> lock(mu_);
      f->spilled = std::move(handle);
      f->data.image.release();
    }
  }

  // The image of a frame, read back from disk when it is there (empty when the read fails or
  // the frame holds none). Producer thread (the only writer of data.image and spilled).
  cv::Mat ImageOf(const Held& f) {
    if (!f.data.image.empty() || !f.spilled) return f.data.image;
    return ReadBack(*f.spilled);
  }
  cv::Mat ImageOf(const ImageRef& ref) {
    if (!ref.image.empty() || !ref.spilled) return ref.image;
    return ReadBack(*ref.spilled);
  }
  cv::Mat ReadBack(const ImageSpill::Handle& handle) {
    ++spill_reads_;
    return spill_->Get(handle);
  }

  // A registered pair as the optimizer keeps it: at most max_ties_per_pair ties, with the
  // patch means at both ends for the radiometric ties (NaN where a patch leaves the image).
  Pair MakePair(const std::shared_ptr<Held>& base, const cv::Mat& base_image,
                const std::shared_ptr<Held>& templ, PairMatch match) const {
    SubsampleTies(&match);
    Pair pair;
    pair.base = base;
    pair.templ = templ;
    pair.base_points = std::move(match.base_points);
    pair.template_points = std::move(match.template_points);
    pair.tie_sigma_px = std::max(options_.tie_sigma_px, match.tie_sigma_px);
    for (size_t t = 0; t < pair.base_points.size(); ++t) {
      pair.base_values.push_back(
          PatchMean(base_image, camera_, pair.base_points[t], options_.tie_patch_radius_px));
      pair.template_values.push_back(PatchMean(templ->data.image, camera_, pair.template_points[t],
                                               options_.tie_patch_radius_px));
    }
    return pair;
  }

  // A frame of the resumed record pushed again: re-registered to the neighbours the record
  // names (the same pairs, the same ties, the recorded pair weights), held with its recorded
  // placement; nothing is rendered, published or solved.
  FramePlacement ReplayPush(const std::shared_ptr<Held>& frame) {
    const int64_t index = frame->data.index;
    const auto found = replay_slots_.find(index);
    if (found == replay_slots_.end()) {
      throw std::invalid_argument(
          "MapFusion::Push: frame " + std::to_string(index) +
          " is replayed (not newer than the resumed record) but the record does not hold it");
    }
    frame->slot = found->second;
    std::vector<Pair> new_pairs;
    std::string note;
    const auto [begin, end] = replay_pairs_.equal_range(index);
    for (auto it = begin; it != end; ++it) {
      const auto base = replay_held_.find(it->second.base);
      if (base == replay_held_.end()) {
        note += "pair with " + std::to_string(it->second.base) + " not replayed; ";
        continue;
      }
      PairMatch match = registrar_(base->second->data, frame->data);
      ++pairs_tried_;
      if (!match.ok) {
        note += "replayed pair with " + std::to_string(it->second.base) +
                " failed: " + match.reason + "; ";
        continue;
      }
      ++pairs_ok_;
      new_pairs.push_back(
          MakePair(base->second, base->second->data.image, frame, std::move(match)));
      *new_pairs.back().weight = it->second.weight;
    }
    replay_held_[index] = frame;
    std::lock_guard<std::mutex> lock(mu_);
    FramePlacement& placement = PlacementAt(frame->slot);
    placement.pos_mosaic_from_image = frame->data.pos_mosaic_from_image;
    placement.note += note;
    frame->rendered = placement;
    frame->painted = true;  // By the run that recorded it, where the record says.
    for (const FusionResumeState::Painted& p : resume_.painted) {
      if (p.index != index) continue;
      frame->rendered.mosaic_from_image = p.mosaic_from_image;
      frame->rendered.gain = p.gain;
      frame->rendered.offset = p.offset;
    }
    window_.push_back(frame);
    for (Pair& p : new_pairs) pairs_.push_back(std::move(p));
    return placement;
  }

  // After the last replayed frame: the window as it was at the record, the solve that was
  // running then, and the optimizer's count towards its next solve.
  void EndReplay() {
    if (!replaying_) return;
    size_t pending_slot = SIZE_MAX;
    {
      std::lock_guard<std::mutex> lock(mu_);
      replaying_ = false;
      while (!window_.empty() && window_.front()->data.index < resume_.held_from) {
        window_.pop_front();
      }
      const auto pending = replay_slots_.find(resume_.solving_through);
      if (pending != replay_slots_.end()) pending_slot = pending->second;
    }
    replay_held_.clear();
    replay_pairs_.clear();
    replay_slots_.clear();
    // The optimizer thread is idle (no frame counted towards a solve during the replay), so the
    // interrupted solve runs here, on the same frames and from the same placements as then.
    if (options_.optimize && pending_slot != SIZE_MAX) SolveWindow(false, pending_slot);
    // The record says where each held frame was painted, but a re-render's tiles reach the disk
    // in the store's slices after the publish that carried the record, so a kill in between
    // left some of them painted elsewhere. Where the disk must show the solution, every held
    // frame is painted again at its placement, with the next publish (a window's renders).
    if (options_.render && options_.optimize && options_.rerender_settled_frames) {
      std::vector<std::pair<std::shared_ptr<Held>, FramePlacement>> held;
      {
        std::lock_guard<std::mutex> lock(mu_);
        for (const auto& f : window_) held.emplace_back(f, PlacementAt(f->slot));
      }
      for (const auto& [f, placement] : held) {
        const cv::Mat image = ImageOf(*f);
        if (image.empty()) continue;
        Render(image, f->data.image_clip, placement, &foreground_);
        {
          std::lock_guard<std::mutex> lock(mu_);
          f->rendered = placement;
        }
        if (sink_) sink_->FramePlaced(placement);
      }
    }
    {
      std::lock_guard<std::mutex> lock(mu_);
      frames_since_solve_ = resume_.frames_since_solve;
      ReleaseImagesLocked();
    }
    if (options_.optimize) cv_.notify_one();
  }

  // Keeps at most max_ties_per_pair tie points, evenly spread over the list (the registrar
  // returns them spread over the overlap), so the optimizer's cost per pair is bounded.
  void SubsampleTies(PairMatch* match) const {
    const size_t n = match->base_points.size();
    const size_t cap = static_cast<size_t>(options_.max_ties_per_pair);
    if (n <= cap) return;
    std::vector<Eigen::Vector2d> base, templ;
    for (size_t k = 0; k < cap; ++k) {
      const size_t i = k * n / cap;
      base.push_back(match->base_points[i]);
      templ.push_back(match->template_points[i]);
    }
    match->base_points = std::move(base);
    match->template_points = std::move(templ);
    // Fewer points carry the pair's information: each one weighs correspondingly more.
    match->tie_sigma_px *= std::sqrt(static_cast<double>(cap) / static_cast<double>(n));
  }

  // Least squares gain/offset mapping the new frame's values onto its neighbours' compensated
  // values, with a weak prior towards (1, 0) so the level cannot wander.
  void FitGain(const std::vector<std::pair<double, double>>& samples, double* gain,
               double* offset) const {
    *gain = 1.0;
    *offset = 0.0;
    if (samples.size() < 6) return;
    double scale = 0.0;
    for (const auto& s : samples) scale += std::abs(s.first);
    scale = std::max(scale / static_cast<double>(samples.size()), 1e-6);
    Eigen::Matrix2d ata = Eigen::Matrix2d::Zero();
    Eigen::Vector2d atb = Eigen::Vector2d::Zero();
    for (const auto& [v, target] : samples) {
      const Eigen::Vector2d row(v / scale, 1.0);
      ata += row * row.transpose();
      atb += row * (target / scale);
    }
    const double w = 1.0 / (options_.gain_prior_sigma * options_.gain_prior_sigma);
    ata(0, 0) += w;
    atb(0) += w;     // gain ~ 1
    ata(1, 1) += w;  // offset/scale ~ 0
    const Eigen::Vector2d x = ata.ldlt().solve(atb);
    if (x.allFinite() && x(0) > 0.2 && x(0) < 5.0) {
      *gain = x(0);
      *offset = x(1) * scale;
    }
  }

  // Registers `templ` to each scored neighbour; up to registration_threads pairs at once (the
  // calling thread takes its share). base_images[k] is neighbour k's image (read back when it
  // is on disk; empty when that failed: the pair fails). Results in the order of `scored`; an
  // exception of any pair is rethrown here, after every pair has finished.
  std::vector<PairMatch> RegisterPairs(
      const std::vector<std::pair<double, std::shared_ptr<Held>>>& scored,
      const std::vector<cv::Mat>& base_images, const FusionFrame& templ) {
    std::vector<PairMatch> matches(scored.size());
    auto one = [&](size_t k) {
      const FusionFrame& base = scored[k].second->data;
      if (base_images[k].empty()) {
        matches[k].reason = spill_
                                ? "its image could not be read back from disk: " + spill_->error()
                                : std::string("it holds no image");
        return;
      }
      if (base.image.data == base_images[k].data) {
        matches[k] = registrar_(base, templ);
        return;
      }
      FusionFrame loaded = base;  // Without pixels (they are on disk): a copy with them.
      loaded.image = base_images[k];
      matches[k] = registrar_(loaded, templ);
    };
    const size_t threads =
        std::min(scored.size(), static_cast<size_t>(options_.registration_threads));
    if (threads <= 1) {
      for (size_t k = 0; k < scored.size(); ++k) one(k);
      return matches;
    }
    std::atomic<size_t> next{0};
    registration_helpers_->Run(threads - 1, [&] {
      for (size_t k = next++; k < scored.size(); k = next++) one(k);
    });
    return matches;
  }

  // Paints a frame's `image` (its own reference: the producer may release the held one
  // meanwhile) with the part `image_clip` at `placement`.
  // `refresh`: the frame was painted before (MosaicSink::Repaint).
  void Render(const cv::Mat& image, const std::vector<Eigen::Vector2d>& image_clip,
              const FramePlacement& placement, Renderer* renderer, bool refresh = false) {
    if (!sink_ || !options_.render) return;
    RenderedFrame frame;
    Prepare(image, image_clip, placement, renderer, &frame);
    PaintPrepared(frame, refresh);
  }

  // A frame ready to paint: its orthoimage with the gain applied and its seam weights, views
  // of the renderer's buffers (valid until that renderer prepares the next frame).
  struct RenderedFrame {
    cv::Mat image, weight;
    cv::Point origin_px;
  };

  void Prepare(const cv::Mat& image, const std::vector<Eigen::Vector2d>& image_clip,
               const FramePlacement& placement, Renderer* renderer, RenderedFrame* frame) {
    // The orthoimage and the weights live in the renderer's buffers (no allocation per frame
    // once warm); the gain is applied in place.
    OrthoImage out;
    renderer->ortho.Run(image, placement.mosaic_from_image, &out, image_clip);
    cv::Mat& compensated = out.image;
    out.image.convertTo(compensated, out.image.type(), placement.gain, placement.offset);
    cv::Mat weight = BufferView(&renderer->weight_backing, out.mask.size(), CV_32F);
    if (camera_.HasDistortion()) {
      cv::Mat distance;
      cv::distanceTransform(out.mask, distance, cv::DIST_L2, cv::DIST_MASK_3, CV_32F);
      distance.convertTo(weight, CV_32F, 1.0 / options_.feather_px);
      cv::min(weight, 1.0, weight);
    } else {
      FeatherWeight(out, &weight);
    }
    frame->image = compensated;
    frame->weight = weight;
    frame->origin_px = out.origin_px;
  }

  void PaintPrepared(const RenderedFrame& frame, bool refresh) {
    if (refresh) {
      sink_->Repaint(frame.image, frame.weight, frame.origin_px);
    } else {
      sink_->Paint(frame.image, frame.weight, frame.origin_px);
    }
  }

  // The final solve's re-renders, `frames` in order, with the orthoimages and weights made on a
  // registration helper thread one frame ahead of the painting on this thread (the two
  // renderers' buffers in turn), so the warps overlap the store's painting; the paints, their
  // order and FramePlaced are as the one-thread loop does them. `done(k)` runs on this thread
  // after frame k is painted.
  void RerenderAhead(const std::vector<std::pair<std::shared_ptr<Held>, FramePlacement>*>& frames,
                     std::map<size_t, ImageRef>& images, const std::function<void(size_t)>& done) {
    Renderer* renderers[2] = {&foreground_, &background_};
    RenderedFrame ready[2];
    bool has_image[2] = {false, false};
    std::mutex mu;
    std::condition_variable changed;
    size_t prepared = 0, painted = 0;
    bool abort = false;
    const std::thread::id painter = std::this_thread::get_id();
    auto stop = [&] {
      std::lock_guard<std::mutex> lock(mu);
      abort = true;
      changed.notify_all();
    };
    registration_helpers_->Run(1, [&] {
      if (std::this_thread::get_id() != painter) {
        for (size_t k = 0; k < frames.size(); ++k) {
          {
            std::unique_lock<std::mutex> lock(mu);
            // Frame k takes the buffers frame k - 2 was painted from.
            changed.wait(lock, [&] { return abort || k < painted + 2; });
            if (abort) return;
          }
          try {
            const auto& [frame, placement] = *frames[k];
            const cv::Mat image = ImageOf(images[frame->slot]);
            has_image[k % 2] = !image.empty();
            if (!image.empty()) {
              Prepare(image, frame->data.image_clip, placement, renderers[k % 2], &ready[k % 2]);
            }
          } catch (...) {
            stop();
            throw;
          }
          std::lock_guard<std::mutex> lock(mu);
          prepared = k + 1;
          changed.notify_all();
        }
        return;
      }
      for (size_t k = 0; k < frames.size(); ++k) {
        {
          std::unique_lock<std::mutex> lock(mu);
          changed.wait(lock, [&] { return abort || prepared > k; });
          if (abort) return;
        }
        try {
          if (has_image[k % 2]) PaintPrepared(ready[k % 2], /*refresh=*/true);
          done(k);
        } catch (...) {
          stop();
          throw;
        }
        std::lock_guard<std::mutex> lock(mu);
        painted = k + 1;
        changed.notify_all();
      }
    });
  }

  // Seam weight of an undistorted frame: its footprint is the convex quadrilateral of the
  // outer pixel edges, where the distance to the border is the least distance to the four
  // edge lines (exact, where distanceTransform approximates it over a whole-image pass):
  // weight = min(1, (distance + 0.5) / feather_px) inside the mask, as distanceTransform
  // measured to the centre of the first pixel outside (src/feather_weight.h).
  void FeatherWeight(const OrthoImage& out, cv::Mat* weight) const {
    const double w = camera_.width, h = camera_.height;
    std::array<Eigen::Vector2d, 4> q;
    const std::array<Eigen::Vector2d, 4> corners = {
        Eigen::Vector2d(-0.5, -0.5), Eigen::Vector2d(w - 0.5, -0.5),
        Eigen::Vector2d(w - 0.5, h - 0.5), Eigen::Vector2d(-0.5, h - 0.5)};
    for (int k = 0; k < 4; ++k) q[k] = ApplyHomography(out.ortho_from_image, corners[k]);
    feather::Weight(q, options_.feather_px, out.mask, weight);
  }

  void StopThread() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      stop_ = true;
    }
    cv_.notify_all();
    if (optimizer_.joinable()) optimizer_.join();
  }

  // Frames a solve ending at push-order position `last_slot` refines. A pure function of the
  // position, so a resumed run's replayed solve refines what the interrupted one did: the whole
  // window when the position falls in the first solve_every_frames of each run of
  // full_window_every x solve_every_frames frames (one background solve in full_window_every
  // when the optimizer keeps up; the next such run when it lags), and the final solve.
  size_t SolveSpan(size_t last_slot, bool final_solve) const {
    const size_t window = static_cast<size_t>(options_.window_frames);
    const size_t every = static_cast<size_t>(options_.solve_every_frames);
    const size_t period = static_cast<size_t>(options_.full_window_every) * every;
    if (final_solve || options_.short_window_frames == 0 || last_slot % period < every) {
      return window;
    }
    return std::min(window, static_cast<size_t>(options_.short_window_frames));
  }

  void OptimizerLoop() {
    // Named so that top -H, perf and gdb attribute its CPU (15 characters at most).
    pthread_setname_np(pthread_self(), "irm-optimizer");
    LowerThisThreadPriority(options_.optimizer_nice);
    std::unique_lock<std::mutex> lock(mu_);
    while (true) {
      cv_.wait(lock,
               [this] { return stop_ || frames_since_solve_ >= options_.solve_every_frames; });
      if (stop_) return;
      lock.unlock();
      SolveWindow(false);
      lock.lock();
    }
  }

  // One window solve: homographies by Ceres, gains by linear least squares; publishes and
  // re-renders what moved. `last_slot` (not SIZE_MAX: a resumed run's interrupted solve, on
  // the producer thread) ends the window at that frame instead of the newest one.
  void SolveWindow(bool final_solve, size_t last_slot = SIZE_MAX) {
    const auto start = Clock::now();
    const double start_cpu_ms = ThreadCpuMs();
    std::vector<std::shared_ptr<Held>> frames;
    std::map<size_t, ImageRef> images;  // slot -> the frame's image, for the re-renders
    std::vector<Pair> pairs;
    std::map<size_t, FramePlacement> current;  // slot -> placement snapshot
    std::map<size_t, Eigen::Matrix<double, 10, 10>> prior_info;
    size_t span = 0;  // Frames refined (SolveSpan).
    {
      std::lock_guard<std::mutex> lock(mu_);
      size_t end = window_.size();
      if (last_slot != SIZE_MAX) {
        end = 0;
        while (end < window_.size() && window_[end]->slot <= last_slot) ++end;
      }
      if (end < 2) return;
      // The last window_frames frames (short_window_frames in most background solves), extended
      // back (up to kMaxHeldWindows windows) to frames no solve has refined yet, so a foreground
      // running ahead never freezes unrefined frames.
      span = SolveSpan(window_[end - 1]->slot, final_solve);
      size_t first = end > span ? end - span : 0;
      while (first > 0 && PlacementAt(window_[first - 1]->slot).optimized_times == 0 &&
             end - first < kMaxHeldWindows * static_cast<size_t>(options_.window_frames)) {
        --first;
      }
      frames.assign(window_.begin() + static_cast<std::ptrdiff_t>(first),
                    window_.begin() + static_cast<std::ptrdiff_t>(end));
      for (const Pair& p : pairs_) {
        if (p.templ->slot >= frames.front()->slot && p.templ->slot <= frames.back()->slot) {
          pairs.push_back(p);
        }
      }
      solving_ = true;  // Until it publishes: a resume record taken meanwhile runs it again.
      solving_first_slot_ = frames.front()->slot;
      solving_last_slot_ = frames.back()->slot;
      solving_min_slot_ = solving_first_slot_;
      for (const Pair& p : pairs) solving_min_slot_ = std::min(solving_min_slot_, p.base->slot);
      solve_reads_from_ = solving_min_slot_;
      for (const Pair& p : pairs) {
        current[p.base->slot] = PlacementAt(p.base->slot);
        current[p.templ->slot] = PlacementAt(p.templ->slot);
      }
      for (const auto& f : frames) {
        current[f->slot] = PlacementAt(f->slot);
        prior_info[f->slot] = f->prior_sqrt_information;
        images[f->slot] = {f->data.image, f->spilled};
      }
      frames_since_solve_ = 0;
    }
    // The placements stay held until this call returns, however it returns.
    struct ReadHold {
      Impl* impl;
      ~ReadHold() {
        std::lock_guard<std::mutex> lock(impl->mu_);
        impl->solve_reads_from_ = SIZE_MAX;
      }
    } read_hold{this};
    const size_t first_slot = frames.front()->slot;
    if (const auto hook = fusion_testing::g_solve_snapshot_hook.load();
        hook && !final_solve && last_slot == SIZE_MAX) {
      hook(frames.front()->data.index, frames.back()->data.index);
    }
    std::map<size_t, std::array<double, 8>> delta;
    for (const auto& [slot, placement] : current) delta[slot].fill(0.0);

    // Stages: least squares from the real-time placements (which may be many sigmas off, where
    // a robust loss would call every tie an outlier), then Cauchy per tie against single bad
    // ties. A whole pair that is wrong by a few pixels is invisible to a per-tie loss: in a
    // loop of four pairs, least squares leaves only a quarter of its error in its own
    // residuals, about one sigma per tie. Its mean residual, though, is many standard errors
    // off, so each pair also gets a weight 1 / (1 + (|mean residual| / pair_robust_scale_px)^2),
    // recomputed after each stage (iteratively reweighted) and kept for the next solve.
    ceres::Problem problem;
    // One residual block per pair, its loss inside (PairTieCost): the same objective as a block
    // per tie under ceres::ScaledLoss, at a fraction of Ceres' per-block work.
    std::vector<double> pair_weight;
    std::vector<TieLoss> tie_loss(pairs.size());
    for (size_t k = 0; k < pairs.size(); ++k) {
      const Pair& p = pairs[k];
      const size_t a = p.base->slot, b = p.templ->slot;
      const double inv_tie = 1.0 / std::max(options_.tie_sigma_px, p.tie_sigma_px);
      pair_weight.push_back(*p.weight);
      tie_loss[k].weight = pair_weight.back();  // Least squares in the first stage.
      if (p.base_points.empty()) continue;
      problem.AddResidualBlock(
          new PairTieCost(current[a].mosaic_from_image, current[b].mosaic_from_image, normalizer_,
                          p.base_points, p.template_points, inv_tie, &tie_loss[k]),
          nullptr, delta[a].data(), delta[b].data());
    }
    const std::array<Eigen::Vector2d, 5> points = {
        Eigen::Vector2d(0, 0), Eigen::Vector2d(camera_.width - 1, 0),
        Eigen::Vector2d(camera_.width - 1, camera_.height - 1),
        Eigen::Vector2d(0, camera_.height - 1),
        Eigen::Vector2d((camera_.width - 1) / 2.0, (camera_.height - 1) / 2.0)};
    for (auto& [slot, d] : delta) {
      if (!problem.HasParameterBlock(d.data())) problem.AddParameterBlock(d.data(), 8);
      if (slot < first_slot) {
        problem.SetParameterBlockConstant(d.data());  // Left the window: frozen.
        continue;
      }
      Eigen::Matrix<double, 10, 1> targets;
      for (int k = 0; k < 5; ++k) {
        targets.segment<2>(2 * k) = ApplyHomography(current[slot].pos_mosaic_from_image, points[k]);
      }
      problem.AddResidualBlock(new PriorCost(current[slot].mosaic_from_image, normalizer_, points,
                                             targets, prior_info.at(slot)),
                               nullptr, d.data());
    }
    ceres::Solver::Options solver;
    ceres::StringToLinearSolverType(options_.linear_solver, &solver.linear_solver_type);
    ceres::StringToSparseLinearAlgebraLibraryType(options_.sparse_library,
                                                  &solver.sparse_linear_algebra_library_type);
    solver.max_num_iterations = final_solve ? 20 : options_.solve_iterations;
    solver.num_threads = 1;
    solver.logging_type = ceres::SILENT;
    // The POS priors are weak next to the ties, so the mode they fix (where the whole window
    // sits) moves the cost by a tiny fraction: Ceres' default tolerances would stop first.
    solver.function_tolerance = 1e-14;
    solver.gradient_tolerance = 1e-16;
    solver.parameter_tolerance = 1e-12;
    ceres::Solver::Summary summary;
    // Pair weights from the mean tie residual of each pair at the current solution.
    auto reweight_pairs = [&] {
      for (size_t k = 0; k < pairs.size(); ++k) {
        const Pair& p = pairs[k];
        const size_t a = p.base->slot, b = p.templ->slot;
        const Eigen::Matrix3d ha =
            ApplyDelta(current[a].mosaic_from_image, normalizer_, delta[a].data());
        const Eigen::Matrix3d hb =
            ApplyDelta(current[b].mosaic_from_image, normalizer_, delta[b].data());
        Eigen::Vector2d mean = Eigen::Vector2d::Zero();
        for (size_t t = 0; t < p.base_points.size(); ++t) {
          mean += ApplyHomography(ha, p.base_points[t]) - ApplyHomography(hb, p.template_points[t]);
        }
        mean /= static_cast<double>(std::max<size_t>(1, p.base_points.size()));
        const double ratio = mean.norm() / options_.pair_robust_scale_px;
        pair_weight[k] = 1.0 / (1.0 + ratio * ratio);
      }
    };
    const int stages = final_solve ? 4 : 2;
    for (int stage = 0; stage < stages; ++stage) {
      if (stage > 0) {
        reweight_pairs();
        for (size_t k = 0; k < pairs.size(); ++k) {
          tie_loss[k] = {pair_weight[k], options_.robust_scale};
        }
      }
      ceres::Solve(solver, &problem, &summary);
    }
    reweight_pairs();
    const double predicted_rmse_px = final_solve && options_.estimate_precision
                                         ? PredictedRmse(&problem, delta, current, first_slot)
                                         : 0.0;
    // Residuals per frame after the solve.
    std::map<size_t, std::pair<double, int>> residual;  // slot -> (sum sq, count)
    std::map<size_t, Eigen::Matrix3d> solved;
    for (auto& [slot, d] : delta) {
      solved[slot] = slot < first_slot
                         ? current[slot].mosaic_from_image
                         : ApplyDelta(current[slot].mosaic_from_image, normalizer_, d.data());
    }
    for (const Pair& p : pairs) {
      for (size_t t = 0; t < p.base_points.size(); ++t) {
        const double e = (ApplyHomography(solved[p.base->slot], p.base_points[t]) -
                          ApplyHomography(solved[p.templ->slot], p.template_points[t]))
                             .squaredNorm();
        for (size_t s : {p.base->slot, p.templ->slot}) {
          residual[s].first += e;
          residual[s].second += 1;
        }
      }
    }
    std::map<size_t, std::pair<double, double>> gains;
    if (options_.compensate_gain) gains = SolveGains(pairs, current, first_slot);

    // Publish, then re-render frames that moved.
    std::vector<std::pair<std::shared_ptr<Held>, FramePlacement>> moved;
    std::vector<std::pair<double, size_t>> candidates;  // (score, index in moved)
    std::set<size_t> settled_slots;                     // Of moved, the settled frames (see below).
    std::set<size_t> forced_slots;  // Of moved, frames that left the fusion meanwhile.
    // Seams on disk (for the lag figures): at each pair's overlap, where the solution puts
    // the two frames against where they were painted. A move both frames share (the window
    // drifting as new POS priors join) leaves the seam as it was.
    std::vector<std::pair<Eigen::Vector2d, Eigen::Vector2d>> overlap(pairs.size());
    for (size_t k = 0; k < pairs.size(); ++k) {
      const Pair& p = pairs[k];
      Eigen::Vector2d pa = Eigen::Vector2d::Zero(), pb = Eigen::Vector2d::Zero();
      for (size_t t = 0; t < p.base_points.size(); ++t) {
        pa += p.base_points[t];
        pb += p.template_points[t];
      }
      const double n = static_cast<double>(std::max<size_t>(1, p.base_points.size()));
      overlap[k] = {pa / n, pb / n};
    }
    // Seam lag of pair k when its frames are placed by `base_h` and `templ_h`.
    auto seam_lag_of = [&](size_t k, const Eigen::Matrix3d& base_h,
                           const Eigen::Matrix3d& templ_h) {
      const Pair& p = pairs[k];
      const auto& [pa, pb] = overlap[k];
      const Eigen::Vector2d lag_a =
          ApplyHomography(base_h, pa) - ApplyHomography(p.base->rendered.mosaic_from_image, pa);
      const Eigen::Vector2d lag_b =
          ApplyHomography(templ_h, pb) - ApplyHomography(p.templ->rendered.mosaic_from_image, pb);
      return (lag_a - lag_b).norm();
    };
    {
      std::lock_guard<std::mutex> lock(mu_);
      // Pair weights are published with the placements (ResumeState reads both).
      for (size_t k = 0; k < pairs.size(); ++k) *pairs[k].weight = pair_weight[k];
      solving_ = false;
      for (const auto& f : frames) {
        FramePlacement& live = PlacementAt(f->slot);
        // Frames placed while we solved were chained from the old placement of their
        // neighbour; carry the correction of the frame itself when it was in the snapshot.
        live.mosaic_from_image = solved[f->slot];
        live.optimized_times += 1;
        if (residual[f->slot].second > 0) {
          live.residual_px = std::sqrt(residual[f->slot].first / residual[f->slot].second);
        }
        if (gains.count(f->slot)) std::tie(live.gain, live.offset) = gains[f->slot];
        if (f->left_fusion) f->moved_after_leaving = live;
        // Compared with the frame as painted, so small moves that add up are re-rendered too.
        double shift = 0.0;
        const double score = PaintLag(f->rendered, live, &shift);
        // A frame the producer has not painted yet is left to the next solve (its first paint
        // would land over this re-render).
        if (score > 1.0 && f->painted) {
          stats_.rerender_candidates += 1;
          if (shift <= 1.0) stats_.radiometric_rerenders += 1;
          // A frame that left the fusion while this solve ran (the caller more than a window
          // ahead) has no later chance: first, whatever the budget and the backlog.
          candidates.emplace_back(f->left_fusion ? std::numeric_limits<double>::infinity() : score,
                                  moved.size());
          if (f->left_fusion) forced_slots.insert(f->slot);
          moved.emplace_back(f, live);
        }
      }
      // The frames that moved most (in units of the thresholds) first.
      std::stable_sort(candidates.begin(), candidates.end(),
                       [](const auto& a, const auto& b) { return a.first > b.first; });
      std::vector<std::pair<std::shared_ptr<Held>, FramePlacement>> by_score;
      for (const auto& [score, k] : candidates) by_score.push_back(moved[k]);
      moved.clear();
      // Before them, frames no solve refines any more (older than the newest window_frames)
      // whose paint still lags their placement, now final: what the disk shows of them would
      // otherwise stay wrong for good (budgets and pauses leave many behind), and one
      // re-render settles them. Oldest first, in flight order: consecutive frames share most
      // of their tiles, which the store then reads back and writes once for several frames.
      // ReleaseImagesLocked holds their images until then.
      if (options_.render && last_slot == SIZE_MAX) {
        const size_t refined = static_cast<size_t>(options_.window_frames);
        for (size_t k = 0; k + refined < window_.size(); ++k) {
          const std::shared_ptr<Held>& f = window_[k];
          if (f->slot >= first_slot) break;
          if (!PaintLagsFinal(*f)) continue;
          moved.emplace_back(f, PlacementAt(f->slot));
          images[f->slot] = {f->data.image, f->spilled};
          settled_slots.insert(f->slot);
          stats_.settled_rerender_candidates += 1;
        }
      }
      // The forced ones (first by score) go before the settled frames.
      const auto forced_end = std::find_if(by_score.begin(), by_score.end(), [&](const auto& m) {
        return forced_slots.count(m.first->slot) == 0;
      });
      moved.insert(moved.begin(), by_score.begin(), forced_end);
      moved.insert(moved.end(), forced_end, by_score.end());
      const double ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
      stats_.solves += 1;
      if (span >= static_cast<size_t>(options_.window_frames)) stats_.full_solves += 1;
      stats_.last_solve_ms = ms;
      stats_.max_solve_ms = std::max(stats_.max_solve_ms, ms);
      stats_.total_solve_ms += ms;
      const double cpu_ms = ThreadCpuMs() - start_cpu_ms;
      stats_.max_solve_cpu_ms = std::max(stats_.max_solve_cpu_ms, cpu_ms);
      stats_.total_solve_cpu_ms += cpu_ms;
      if (predicted_rmse_px > 0.0) stats_.predicted_rmse_px = predicted_rmse_px;
    }
    // Re-render, settled frames and then the frames that moved most. A background solve pauses
    // while the output is behind (new frames first); what it leaves keeps its painted placement and
    // is a candidate of the next solve.
    Renderer* renderer = final_solve || last_slot != SIZE_MAX ? &foreground_ : &background_;
    const bool may_defer = renderer == &background_ && options_.max_output_backlog_s > 0.0;
    // At most max_rerenders_per_solve of them in a background solve (the final solve does
    // them all). A settled frame's tiles have mostly left the store's cache (read back,
    // rewritten, their overviews too), so settled frames go only while the output is less
    // than half max_output_backlog_s behind, and the frames that moved take their turn:
    // at full load the writer keeps to the newest frames as without them.
    const size_t budget = final_solve ? 0 : static_cast<size_t>(options_.max_rerenders_per_solve);
    size_t rendered_count = 0, settled_rendered = 0;
    // The final solve re-renders every frame that moved (no budget, no backlog): with a helper
    // thread idle, the next frame's warp runs beside this one's painting.
    bool rendered_ahead = false;
    if (final_solve && last_slot == SIZE_MAX && registration_helpers_ && sink_ && options_.render &&
        moved.size() >= 2) {
      std::vector<std::pair<std::shared_ptr<Held>, FramePlacement>*> chosen;
      for (auto& m : moved) {
        if (settled_slots.count(m.first->slot) > 0) {
          std::lock_guard<std::mutex> lock(mu_);
          if (m.first->left_fusion) continue;
        }
        chosen.push_back(&m);
      }
      RerenderAhead(chosen, images, [&](size_t k) {
        const auto& [frame, placement] = *chosen[k];
        std::lock_guard<std::mutex> records(records_mu_);
        {
          std::lock_guard<std::mutex> lock(mu_);
          frame->rendered = placement;
        }
        sink_->FramePlaced(placement);
        ++rendered_count;
        settled_rendered += settled_slots.count(frame->slot) > 0 ? 1 : 0;
      });
      rendered_ahead = true;
    }
    for (const auto& [frame, placement] : moved) {
      if (rendered_ahead) break;
      const bool forced = forced_slots.count(frame->slot) > 0;
      if (!forced && budget > 0 && rendered_count >= budget) break;
      const double backlog_s = may_defer && sink_ ? sink_->OutputBacklogSeconds() : 0.0;
      if (!forced && backlog_s > options_.max_output_backlog_s) break;
      const bool settled = settled_slots.count(frame->slot) > 0;
      if (settled) {
        if (backlog_s > 0.5 * options_.max_output_backlog_s) continue;
        std::lock_guard<std::mutex> lock(mu_);
        if (frame->left_fusion) continue;  // Push has re-rendered it (or is doing so) as it left.
      }
      const cv::Mat image = ImageOf(images[frame->slot]);
      if (!image.empty())
        Render(image, frame->data.image_clip, placement, renderer, /*refresh=*/true);
      // After any record Push writes of an older placement (RenderSettled).
      std::lock_guard<std::mutex> records(records_mu_);
      {
        std::lock_guard<std::mutex> lock(mu_);
        frame->rendered = placement;
      }
      if (sink_) sink_->FramePlaced(placement);
      ++rendered_count;
      settled_rendered += settled ? 1 : 0;
    }
    {
      std::lock_guard<std::mutex> lock(mu_);
      stats_.rerendered_frames += static_cast<int64_t>(rendered_count);
      if (rendered_ahead) stats_.rerendered_ahead += static_cast<int64_t>(rendered_count);
      stats_.settled_rerenders += static_cast<int64_t>(settled_rendered);
      // The budget's re-renders the output's backlog left to the next solve.
      const size_t chosen = budget > 0 ? std::min(budget, moved.size()) : moved.size();
      stats_.deferred_rerenders += static_cast<int64_t>(chosen - std::min(chosen, rendered_count));
      if (!final_solve && last_slot == SIZE_MAX) {
        // The lag the disk keeps after this solve's re-renders (re-rendered frames have none).
        double painted_sum_sq = 0.0;
        for (const auto& f : frames) {
          const double lag = CornerShift(f->rendered.mosaic_from_image,
                                         PlacementAt(f->slot).mosaic_from_image, camera_);
          painted_sum_sq += lag * lag;
        }
        double seam_after_sq = 0.0;
        int seam_count = 0;
        for (size_t k = 0; k < pairs.size(); ++k) {
          if (pairs[k].base_points.empty()) continue;
          const double lag = seam_lag_of(k, PlacementAt(pairs[k].base->slot).mosaic_from_image,
                                         PlacementAt(pairs[k].templ->slot).mosaic_from_image);
          seam_after_sq += lag * lag;
          ++seam_count;
        }
        const double n = static_cast<double>(lag_solves_++);
        const double painted_rms = std::sqrt(painted_sum_sq / std::max<size_t>(1, frames.size()));
        const double seam_rms = std::sqrt(seam_after_sq / std::max(1, seam_count));
        stats_.mean_painted_lag_px = (stats_.mean_painted_lag_px * n + painted_rms) / (n + 1);
        stats_.mean_seam_lag_px = (stats_.mean_seam_lag_px * n + seam_rms) / (n + 1);
      }
    }
  }

  // Root mean of the expected squared placement error of the frames from `first_slot` on, from
  // the covariance of the solved problem (Ceres; inverse of J^T J at the solution): a 5x5 grid
  // of each frame's pixels, mapped through the Jacobian of its placement.
  double PredictedRmse(ceres::Problem* problem, std::map<size_t, std::array<double, 8>>& delta,
                       std::map<size_t, FramePlacement>& current, size_t first_slot) const {
    ceres::Covariance covariance{ceres::Covariance::Options()};
    std::vector<std::pair<const double*, const double*>> blocks;
    for (auto& [slot, d] : delta) {
      if (slot >= first_slot) blocks.emplace_back(d.data(), d.data());
    }
    if (blocks.empty() || !covariance.Compute(blocks, problem)) return 0.0;
    double sum = 0.0;
    int frames = 0;
    for (auto& [slot, d] : delta) {
      if (slot < first_slot) continue;
      Eigen::Matrix<double, 8, 8, Eigen::RowMajor> c;
      covariance.GetCovarianceBlock(d.data(), d.data(), c.data());
      double trace = 0.0;
      for (int j = 0; j < 5; ++j) {
        for (int i = 0; i < 5; ++i) {
          const Eigen::Vector2d p((camera_.width - 1) * i / 4.0, (camera_.height - 1) * j / 4.0);
          Eigen::Matrix<double, 2, 8> jacobian;
          for (int k = 0; k < 8; ++k) {
            std::array<double, 8> plus = d, minus = d;
            plus[k] += 1e-6;
            minus[k] -= 1e-6;
            const Eigen::Matrix3d& h = current[slot].mosaic_from_image;
            jacobian.col(k) = (ApplyHomography(ApplyDelta(h, normalizer_, plus.data()), p) -
                               ApplyHomography(ApplyDelta(h, normalizer_, minus.data()), p)) /
                              2e-6;
          }
          trace += (jacobian * c * jacobian.transpose()).trace();
        }
      }
      sum += trace / 25.0;
      ++frames;
    }
    return std::sqrt(sum / frames);
  }

  // Gains and offsets of the window's frames from the radiometric ties (linear least squares,
  // frozen frames fixed, weak prior towards gain 1 and offset 0).
  std::map<size_t, std::pair<double, double>> SolveGains(
      const std::vector<Pair>& pairs, const std::map<size_t, FramePlacement>& current,
      size_t first_slot) const {
    std::map<size_t, int> unknown;  // slot -> column pair index
    for (const auto& [slot, placement] : current) {
      if (slot >= first_slot) {
        const int next = static_cast<int>(unknown.size());
        unknown[slot] = next;
      }
    }
    double scale = 0.0;
    int count = 0;
    for (const Pair& p : pairs) {
      for (double v : p.base_values) {
        if (std::isfinite(v)) {
          scale += std::abs(v);
          ++count;
        }
      }
    }
    if (count < 6 || unknown.empty()) return {};
    scale = std::max(scale / count, 1e-6);
    // The normal equations are sparse (a frame's gain and offset couple to its pairs' frames
    // only); a dense factorization grows with the cube of the frames (600 unknowns in a solve
    // of the whole window).
    const int n = static_cast<int>(unknown.size()) * 2;
    std::vector<Eigen::Triplet<double>> ata;  // Summed where they repeat.
    Eigen::VectorXd atb = Eigen::VectorXd::Zero(n);
    for (const Pair& p : pairs) {
      // The pair's equations summed over its ties first (gain and offset of the base, then of
      // the template), each frame either unknown (its column) or fixed (its values).
      int column[2] = {-1, -1};
      double fixed_gain[2] = {1.0, 1.0}, fixed_offset[2] = {0.0, 0.0};
      const size_t slots[2] = {p.base->slot, p.templ->slot};
      for (int f = 0; f < 2; ++f) {
        const auto it = unknown.find(slots[f]);
        if (it != unknown.end()) {
          column[f] = 2 * it->second;
        } else {
          const FramePlacement& fixed = current.at(slots[f]);
          fixed_gain[f] = fixed.gain;
          fixed_offset[f] = fixed.offset / scale;
        }
      }
      if (column[0] < 0 && column[1] < 0) continue;
      Eigen::Matrix4d block = Eigen::Matrix4d::Zero();
      Eigen::Vector4d rhs_block = Eigen::Vector4d::Zero();
      for (size_t t = 0; t < p.base_values.size(); ++t) {
        const double v[2] = {p.base_values[t] / scale, p.template_values[t] / scale};
        if (!std::isfinite(v[0]) || !std::isfinite(v[1])) continue;
        // Equation: gain_a va + off_a - gain_b vb - off_b = 0; a fixed frame's terms go right.
        Eigen::Vector4d row = Eigen::Vector4d::Zero();
        double rhs = 0.0;
        for (int f = 0; f < 2; ++f) {
          const double sign = f == 0 ? 1.0 : -1.0;
          if (column[f] >= 0) {
            row(2 * f) = sign * v[f];
            row(2 * f + 1) = sign;
          } else {
            rhs -= sign * (fixed_gain[f] * v[f] + fixed_offset[f]);
          }
        }
        block.noalias() += row * row.transpose();
        rhs_block += row * rhs;
      }
      for (int i = 0; i < 4; ++i) {
        if (column[i / 2] < 0) continue;
        atb(column[i / 2] + i % 2) += rhs_block(i);
        for (int j = 0; j < 4; ++j) {
          if (column[j / 2] >= 0) {
            ata.emplace_back(column[i / 2] + i % 2, column[j / 2] + j % 2, block(i, j));
          }
        }
      }
    }
    const double w = 1.0 / (options_.gain_prior_sigma * options_.gain_prior_sigma);
    for (int k = 0; k < n / 2; ++k) {
      ata.emplace_back(2 * k, 2 * k, w);
      atb(2 * k) += w;
      ata.emplace_back(2 * k + 1, 2 * k + 1, w);
    }
    Eigen::SparseMatrix<double> normal(n, n);
    normal.setFromTriplets(ata.begin(), ata.end());
    const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> factor(normal);
    if (factor.info() != Eigen::Success) return {};
    const Eigen::VectorXd x = factor.solve(atb);
    std::map<size_t, std::pair<double, double>> result;
    if (!x.allFinite()) return result;
    for (const auto& [slot, k] : unknown) {
      const double g = x(2 * k);
      if (g > 0.2 && g < 5.0) result[slot] = {g, x(2 * k + 1) * scale};
    }
    return result;
  }

  static constexpr size_t kMaxHeldWindows = 4;
  int64_t lag_solves_ = 0;  // Background solves averaged into the lag figures (under mu_).

  FusionOptions options_;
  CameraModel camera_;
  PairRegisterFn registrar_;
  MosaicSink* sink_;
  Normalizer normalizer_;
  // A renderer per thread that paints: the caller's (new frames, the final solve) and the
  // optimizer's (re-renders).
  struct Renderer {
    // Painting reads the orthoimage where the weights are above 0 only, inside the footprint.
    explicit Renderer(const CameraModel& camera) : ortho(camera, FootprintOnly()) {
      ortho.set_reuse_output(true);
    }
    static OrthoOptions FootprintOnly() {
      OrthoOptions options;
      options.footprint_only = true;
      return options;
    }
    Orthorectifier ortho;
    cv::Mat weight_backing;
  };
  Renderer foreground_;
  Renderer background_;

  mutable std::mutex mu_;
  // Orders the sink's records of re-rendered frames (RenderSettled); taken before mu_.
  std::mutex records_mu_;
  std::condition_variable cv_;
  bool stop_ = false;
  std::thread optimizer_;
  // Threads that register a new frame's other pairs beside the caller (registration_threads
  // - 1 of them), started once: none when registration_threads is 1.
  std::unique_ptr<HelperThreads> registration_helpers_;
  std::deque<std::shared_ptr<Held>> window_;
  std::deque<Pair> pairs_;
  // Every frame's placement from slot base_slot_ on (ReleasePlacements drops older ones whose
  // caller keeps them elsewhere): a deque, so an hour's ~90,000 grow in blocks instead of a
  // vector's doubling, and a front that goes costs nothing.
  std::deque<FramePlacement> placements_;
  size_t base_slot_ = 0;
  FramePlacement& PlacementAt(size_t slot) { return placements_[slot - base_slot_]; }
  const FramePlacement& PlacementAt(size_t slot) const { return placements_[slot - base_slot_]; }
  int64_t frames_since_solve_ = 0;
  int64_t frames_registered_ = 0, frames_pos_only_ = 0;
  // Counted by the producer outside mu_ (registration runs unlocked), read by stats() anywhere.
  std::atomic<int64_t> pairs_tried_{0}, pairs_ok_{0};
  FusionStats stats_;
  // A solve between its snapshot and its publish, and the push-order span of its frames.
  bool solving_ = false;
  size_t solving_first_slot_ = 0, solving_last_slot_ = 0;
  size_t solving_min_slot_ = 0;  // Oldest slot its snapshot holds (a pair's base may be older).
  // Oldest placement a solve still reads, SIZE_MAX when none runs. Unlike solving_, it holds
  // past the publish, through the re-renders, to the solve's last look at its frames and
  // pairs (the lag it leaves on disk): the caller releases placements meanwhile.
  size_t solve_reads_from_ = SIZE_MAX;

  // Resumed runs (Resume): the record, without its placements (they are placements_), and
  // while its frames are pushed again, what the replay needs (producer thread only, except
  // replaying_ which ResumeState reads under mu_).
  FusionResumeState resume_;
  bool replaying_ = false;
  int64_t replay_last_ = -1;                                      // Newest recorded frame.
  std::map<int64_t, size_t> replay_slots_;                        // Replayed frame -> its slot.
  std::multimap<int64_t, FusionResumeState::Pair> replay_pairs_;  // Template -> its pairs.
  std::map<int64_t, std::shared_ptr<Held>> replay_held_;          // Frames pushed again.

  // Held images on disk (FusionOptions::images_in_memory > 0), and how many were read back.
  std::unique_ptr<ImageSpill> spill_;
  std::atomic<int64_t> spill_reads_{0};
};

int64_t FusionResumeState::ReplayFrom() const {
  int64_t from = held_from;
  for (const Pair& p : pairs) {
    if (p.base >= 0 && (from < 0 || p.base < from)) from = p.base;
  }
  return from;
}

MapFusion::MapFusion(FusionOptions options, CameraModel camera, PairRegisterFn registrar,
                     MosaicSink* sink)
    : impl_(std::make_unique<Impl>(options, std::move(camera), std::move(registrar), sink)) {}
MapFusion::~MapFusion() = default;
FramePlacement MapFusion::Push(FusionFrame frame) { return impl_->Push(std::move(frame)); }
void MapFusion::Finish() { impl_->Finish(); }
std::vector<FramePlacement> MapFusion::Placements() const { return impl_->Placements(); }
size_t MapFusion::ReleasePlacements(size_t before_slot) {
  return impl_->ReleasePlacements(before_slot);
}
FusionResumeState MapFusion::ResumeState(size_t from_slot) const {
  return impl_->ResumeState(from_slot);
}
void MapFusion::Resume(FusionResumeState state) { impl_->Resume(std::move(state)); }
FusionStats MapFusion::stats() const { return impl_->stats(); }

}  // namespace irmosaic
