// What a simulated unit knows and a real one cannot: the true contact force per fluid cell and
// the finger's true indentation. The bridge scores its rendering against it when one is given
// (mrskin::sim::MockDeviceTruth on the mock).
#pragma once

#include <span>

#include "mrskin/driver/export.hpp"

namespace mrskin {

class MRSKIN_DRIVER_API ForceTruth {
 public:
  ForceTruth() = default;
  ForceTruth(const ForceTruth&) = delete;
  ForceTruth& operator=(const ForceTruth&) = delete;
  ForceTruth(ForceTruth&&) = delete;
  ForceTruth& operator=(ForceTruth&&) = delete;
  virtual ~ForceTruth() = default;
  // The true contact force per fluid cell, N.
  virtual void true_forces(std::span<double> out_N) const noexcept = 0;
  // The finger's true indentation per fluid cell, m, so that scoring follows the finger's true
  // motion rather than the controller's own reading of it; false when unknown.
  virtual bool finger_indentation(std::span<double> /*out_m*/) const noexcept { return false; }
};

}  // namespace mrskin
