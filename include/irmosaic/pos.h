#pragma once

#include <Eigen/Geometry>
#include <optional>
#include <string>
#include <vector>

#include "irmosaic/export.h"

namespace irmosaic {

// One POS sample as logged: WGS84 position and aircraft attitude, plus the camera mount
// (gimbal) angles. Angle conventions: docs/conventions.md.
struct PosRecord {
  double time_s = 0.0;
  double lat_deg = 0.0;
  double lon_deg = 0.0;
  double height_m = 0.0;  // Ellipsoidal height.
  double roll_deg = 0.0;
  double pitch_deg = 0.0;
  double yaw_deg = 0.0;           // Heading, clockwise from true north.
  double gimbal_roll_deg = 0.0;   // Sweep angle: rotation of the mount about the body x axis.
  double gimbal_pitch_deg = 0.0;  // Tilt of the mount about its y axis.
  double gimbal_yaw_deg = 0.0;    // Pan of the mount about its z axis.
};

// A pose at an instant: geodetic position and rotations as unit quaternions.
struct Pose {
  double lat_deg = 0.0;
  double lon_deg = 0.0;
  double height_m = 0.0;
  Eigen::Quaterniond ned_from_body = Eigen::Quaterniond::Identity();
  Eigen::Quaterniond body_from_mount = Eigen::Quaterniond::Identity();
};

// Converts logged angles to rotations (Z-Y-X Tait-Bryan, aerospace order).
IRMOSAIC_EXPORT Pose PoseFromRecord(const PosRecord& record);

// Rotation yaw-pitch-roll (degrees) as R = Rz(yaw) * Ry(pitch) * Rx(roll).
IRMOSAIC_EXPORT Eigen::Quaterniond RotationFromYpr(double yaw_deg, double pitch_deg,
                                                   double roll_deg);

// Result of looking a pose up at a time.
struct PoseLookup {
  enum class Status { kOk, kBeforeStart, kAfterEnd, kInGap };
  Status status = Status::kOk;
  Pose pose;            // Valid only when status == kOk.
  std::string message;  // Why not, when status != kOk.

  bool ok() const { return status == Status::kOk; }
};

// A time-ordered POS log with interpolation to frame times.
class IRMOSAIC_EXPORT PosTrack {
 public:
  struct Options {
    // Frames further than this from any POS sample (inside a gap) get kInGap.
    double max_gap_s = 1.0;
  };

  // Reads the CSV format of docs/formats.md. Throws InputError naming file, line and column.
  static PosTrack LoadCsv(const std::string& path, const Options& options);
  static PosTrack LoadCsv(const std::string& path) { return LoadCsv(path, Options()); }

  // Builds from records (validated as the CSV is); `source` names them in errors.
  static PosTrack FromRecords(std::vector<PosRecord> records, const std::string& source,
                              const Options& options);

  // Writes the CSV format of docs/formats.md (full double precision).
  void WriteCsv(const std::string& path) const;

  // Pose at time_s: position linear in the local ENU frame of the first record, attitude by
  // quaternion slerp. Never extrapolates: outside the range or in a gap it reports why.
  PoseLookup At(double time_s) const;

  const std::vector<PosRecord>& records() const { return records_; }
  bool empty() const { return records_.empty(); }
  const Options& options() const { return options_; }

 private:
  std::vector<PosRecord> records_;
  Options options_;
};

}  // namespace irmosaic
