#pragma once

// A simulated sweep for map fusion tests and benchmarks: true and POS homographies of a
// boustrophedon sweep, and an ideal registrar that returns true tie points with noise.
#include <Eigen/Core>
#include <cmath>
#include <memory>
#include <mutex>
#include <opencv2/calib3d.hpp>
#include <random>
#include <vector>

#include "irmosaic/frame_geometry.h"
#include "irmosaic/map_fusion.h"

namespace irmosaic::testing {

// A boustrophedon sweep: `per_sweep` frames across track, sweeps 85 % of a footprint apart.
struct Sweep {
  CameraModel camera = DefaultInfraredCamera();
  LocalFrame frame{47.2, 8.5};
  MosaicGrid grid{1000.0 / 2400.0};
  std::vector<Eigen::Matrix3d> truth, pos;
  std::vector<Eigen::Matrix<double, 10, 10>> prior;
  double pos_sigma_px = 0.0;
};

inline Sweep MakeSweep(int frames, int per_sweep, double pos_sigma_m, double att_sigma_deg,
                       uint32_t seed) {
  Sweep s;
  std::mt19937 rng(seed);
  std::normal_distribution<double> pos_noise(0.0, pos_sigma_m), att_noise(0.0, att_sigma_deg);
  const double altitude = 1000.0;
  const double along_m = 0.85 * altitude * s.camera.height / s.camera.fx;
  for (int i = 0; i < frames; ++i) {
    const int sweep = i / per_sweep, k = i % per_sweep;
    const int step = sweep % 2 == 0 ? k : per_sweep - 1 - k;
    const double angle = (step - (per_sweep - 1) / 2.0) * 11.0;
    const Eigen::Vector3d geo = s.frame.GeodeticFromEnu({0.0, sweep * along_m, 0.0});
    PosRecord truth{i * 0.04, geo.x(), geo.y(), altitude, 0.0, 0.0, 0.0, angle, 0.0, 0.0};
    PosRecord measured = truth;
    const Eigen::Vector3d noisy =
        s.frame.GeodeticFromEnu({pos_noise(rng), sweep * along_m + pos_noise(rng), 0.0});
    measured.lat_deg = noisy.x();
    measured.lon_deg = noisy.y();
    measured.height_m = altitude + pos_noise(rng);
    measured.roll_deg += att_noise(rng);
    measured.pitch_deg += att_noise(rng);
    measured.yaw_deg += att_noise(rng);
    const FlatGround ground(0.0);
    const FrameGeometry gt =
        ComputeFrameGeometry(s.camera, PoseFromRecord(truth), s.frame, s.grid, ground);
    const FrameGeometry gp =
        ComputeFrameGeometry(s.camera, PoseFromRecord(measured), s.frame, s.grid, ground);
    if (!gt.ok || !gp.ok) std::abort();
    s.truth.push_back(gt.mosaic_from_image);
    s.pos.push_back(gp.mosaic_from_image);
    s.prior.push_back(PosPriorSqrtInformation(s.camera, PoseFromRecord(measured), s.frame, s.grid,
                                              ground, pos_sigma_m, att_sigma_deg, 0.2));
  }
  s.pos_sigma_px = std::hypot(pos_sigma_m, altitude * att_sigma_deg * M_PI / 180.0) / s.grid.gsd_m;
  return s;
}

// RMSE (mosaic px) of a 5x5 grid of the frame's pixels placed by `h` against the truth.
// Frame i of the sweep as the fusion takes it: POS placement and prior of pose i, 25 fps.
inline FusionFrame SweepFrame(const Sweep& s, int64_t i, const cv::Mat& image) {
  FusionFrame f;
  f.index = i;
  f.time_s = static_cast<double>(i) * 0.04;
  f.image = image;
  f.pos_mosaic_from_image = s.pos[static_cast<size_t>(i)];
  f.prior_sqrt_information = s.prior[static_cast<size_t>(i)];
  return f;
}

inline double PlacementRmse(const Eigen::Matrix3d& h, const Eigen::Matrix3d& truth,
                            const CameraModel& camera) {
  double sum = 0.0;
  for (int j = 0; j < 5; ++j)
    for (int i = 0; i < 5; ++i) {
      const Eigen::Vector2d p((camera.width - 1) * i / 4.0, (camera.height - 1) * j / 4.0);
      sum += (ApplyHomography(h, p) - ApplyHomography(truth, p)).squaredNorm();
    }
  return std::sqrt(sum / 25.0);
}

// Ties from the true relative homography on a grid inside the overlap, with Gaussian noise;
// the pair `corrupt` (base, template) gets `corrupt_px` added to every base point's x.
inline PairRegisterFn IdealRegistrar(const Sweep& s, double noise_px, uint32_t seed,
                                     std::pair<int64_t, int64_t> corrupt = {-1, -1},
                                     double corrupt_px = 12.0) {
  auto rng = std::make_shared<std::mt19937>(seed);
  auto mu = std::make_shared<std::mutex>();
  return [&s, noise_px, rng, mu, corrupt, corrupt_px](const FusionFrame& base,
                                                      const FusionFrame& templ) {
    std::lock_guard<std::mutex> lock(*mu);
    std::normal_distribution<double> noise(0.0, noise_px);
    const Eigen::Matrix3d base_from_templ = s.truth[base.index].inverse() * s.truth[templ.index];
    PairMatch m;
    for (int y = 8; y < s.camera.height; y += 40) {
      for (int x = 8; x < s.camera.width; x += 40) {
        const Eigen::Vector2d pt(x, y);
        Eigen::Vector2d pb = ApplyHomography(base_from_templ, pt);
        if (pb.x() < 8 || pb.y() < 8 || pb.x() > s.camera.width - 8 ||
            pb.y() > s.camera.height - 8) {
          continue;
        }
        if (base.index == corrupt.first && templ.index == corrupt.second) pb.x() += corrupt_px;
        // One draw a statement, y first: a call's argument order is unspecified, and every
        // compiler must draw the same ties.
        const double ty = noise(*rng);
        m.template_points.push_back(pt + Eigen::Vector2d(noise(*rng), ty));
        const double by = noise(*rng);
        m.base_points.push_back(pb + Eigen::Vector2d(noise(*rng), by));
      }
    }
    m.ok = m.base_points.size() >= 8;
    if (!m.ok) m.reason = "too little overlap";
    m.base_from_template = base_from_templ;
    return m;
  };
}

// Ties from the true relative homography on a grid inside the overlap, with 0.2 px of noise
// seeded by the pair alone: the same ties whatever the order or thread of the calls.
inline PairMatch PairSeededTies(const Sweep& s, const FusionFrame& base, const FusionFrame& templ) {
  std::mt19937 rng(static_cast<uint32_t>(base.index * 1000 + templ.index));
  std::normal_distribution<double> noise(0.0, 0.2);
  const Eigen::Matrix3d base_from_templ = s.truth[base.index].inverse() * s.truth[templ.index];
  PairMatch m;
  for (int y = 8; y < s.camera.height; y += 40) {
    for (int x = 8; x < s.camera.width; x += 40) {
      const Eigen::Vector2d pb = ApplyHomography(base_from_templ, {x, y});
      if (pb.x() < 8 || pb.y() < 8 || pb.x() > s.camera.width - 8 || pb.y() > s.camera.height - 8) {
        continue;
      }
      const double ty = y + noise(rng);  // One draw a statement (argument order is unspecified).
      m.template_points.emplace_back(x + noise(rng), ty);
      const double by = pb.y() + noise(rng);
      m.base_points.emplace_back(pb.x() + noise(rng), by);
    }
  }
  m.ok = m.base_points.size() >= 8;
  if (!m.ok) m.reason = "too little overlap";
  m.base_from_template = base_from_templ;
  return m;
}

// Placement RMSE after removing the best global similarity between run and truth: how well
// the frames fit each other (seams), apart from where POS put the whole mosaic.
inline std::vector<double> RelativeRmse(const std::vector<FramePlacement>& placements,
                                        const Sweep& s) {
  std::vector<cv::Point2f> run_pts, true_pts;
  const Eigen::Vector2d centre((s.camera.width - 1) / 2.0, (s.camera.height - 1) / 2.0);
  for (const FramePlacement& p : placements) {
    const Eigen::Vector2d a = ApplyHomography(p.mosaic_from_image, centre);
    const Eigen::Vector2d b = ApplyHomography(s.truth[p.index], centre);
    run_pts.emplace_back(static_cast<float>(a.x()), static_cast<float>(a.y()));
    true_pts.emplace_back(static_cast<float>(b.x()), static_cast<float>(b.y()));
  }
  const cv::Mat sim = cv::estimateAffinePartial2D(run_pts, true_pts, cv::noArray(), cv::LMEDS);
  Eigen::Matrix3d g = Eigen::Matrix3d::Identity();
  for (int r = 0; r < 2; ++r)
    for (int c = 0; c < 3; ++c) g(r, c) = sim.at<double>(r, c);
  std::vector<double> rmse;
  for (const FramePlacement& p : placements) {
    rmse.push_back(PlacementRmse(g * p.mosaic_from_image, s.truth[p.index], s.camera));
  }
  return rmse;
}

// Seam misalignment between frames i and j: points of j, placed by j's homography and by i's
// (through the truth), differ by this RMS (mosaic px). What a viewer sees at the seam.
inline double SeamRmse(const std::vector<FramePlacement>& placements, const Sweep& s, int64_t i,
                       int64_t j) {
  double sum = 0.0;
  int n = 0;
  for (int y = 0; y < s.camera.height; y += 64) {
    for (int x = 0; x < s.camera.width; x += 64) {
      const Eigen::Vector2d p(x, y);
      const Eigen::Vector2d q = ApplyHomography(s.truth[i].inverse() * s.truth[j], p);
      if (q.x() < 0 || q.y() < 0 || q.x() > s.camera.width - 1 || q.y() > s.camera.height - 1) {
        continue;
      }
      sum += (ApplyHomography(placements[j].mosaic_from_image, p) -
              ApplyHomography(placements[i].mosaic_from_image, q))
                 .squaredNorm();
      ++n;
    }
  }
  return n > 0 ? std::sqrt(sum / n) : 0.0;
}

}  // namespace irmosaic::testing
