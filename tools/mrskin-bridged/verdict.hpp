// The run's verdict against the product's figures (docs/requirements.md, docs/daemon.md
// "Verdict"): the rendered-force error, real time and the bus, each met or not, with a plain
// explanation of every figure beyond its limit. The last line is the verdict itself.
#pragma once

#include <string>
#include <vector>

#include "mrskin/bridge/stats.hpp"

namespace mrskin::bridged {

struct VerdictLimits {
  // RMS rendered-force error, loading and holding: on the default unit; a unit of another design
  // point holds it times its force scale (bridge::DesignScale: 0.4 mN on fingertip-16x16).
  double rms_error_N = 0.04;
  double relative_p95 = 0.07;  // 95th-percentile relative error where the target >= the scorer's floor
  double bus_load = 0.80;      // of the bus's capacity: each direction on USB, both on CAN FD
  // CAN is one bus both directions share: their loads together, of its capacity. Classic CAN is
  // held to half of it (docs/requirements.md: a typical palpation scene), CAN FD to bus_load.
  double classic_can_load = 0.50;
  double reports_per_frame = 1.0;  // counted on an unmodelled link: a full-speed frame carries one
};

// truth_scored: the statistics' errors are against the device's true force (the mock); without
// it they are not the product's figure and the rendering is "not scored". period_s: the tick
// period, to tell a tick that outgrew its period from a machine too busy to wake on time.
std::vector<std::string> verdict_lines(const bridge::BridgeStats& stats, bool truth_scored, double period_s,
                                       const VerdictLimits& limits = {});

}  // namespace mrskin::bridged
