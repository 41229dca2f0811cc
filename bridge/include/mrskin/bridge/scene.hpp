// Scripted scenes: a simulated finger on the skin and the slave robot's palpation stream,
// driven by one script so that every scene yields a measurable rendered-force error.
#pragma once

#include <memory>
#include <span>
#include <string_view>

#include "mrskin/bridge/export.hpp"
#include "mrskin/bridge/mapping.hpp"
#include "mrskin/bridge/tissue.hpp"
#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/layout.hpp"

namespace mrskin::bridge {

// One slave-side sample: what the instrument feels.
struct SlaveSample {
  TimePoint stamp{};           // when the robot sampled it
  TimePoint received{};        // when it reached this host, on the loop's clock (0: at stamp)
  double force_N = 0.0;        // normal contact force on the tissue
  double indentation_m = 0.0;  // instrument indentation into the tissue
  // Where the instrument touches, in the slave's tissue frame (WorkspaceMapping takes it to the
  // skin), and the instrument tip's radius.
  double contact_x_m = 0.0;
  double contact_y_m = 0.0;
  double tip_radius_m = 0.0;
  bool valid = false;
  // The stream's publisher went away (a DDS writer lost): the bridge fades at once rather than
  // after the stale policy's hold. The fields repeat the last sample.
  bool ended = false;
};

// Produces the latest slave sample; called from the tick thread, never blocks.
class MRSKIN_BRIDGE_API SlaveSource {
 public:
  SlaveSource() = default;
  SlaveSource(const SlaveSource&) = delete;
  SlaveSource& operator=(const SlaveSource&) = delete;
  SlaveSource(SlaveSource&&) = delete;
  SlaveSource& operator=(SlaveSource&&) = delete;
  virtual ~SlaveSource() = default;
  // Fills out with the newest sample at or before now; false when there is none.
  virtual bool latest(TimePoint now, SlaveSample& out) noexcept = 0;
};

// The slave side at a scene time without the stream's sampling and noise: the ground truth that
// tests hold the stream and the bridge's estimate against.
struct SlaveTruth {
  double contact_x_m = 0.0;  // the slave's tissue frame
  double contact_y_m = 0.0;
  double indentation_m = 0.0;
  double rate_m_per_s = 0.0;  // d(indentation)/dt
  double force_N = 0.0;       // tissue_at(contact).force_N(indentation, rate)
};

// A scene scripts both sides from t = 0 (its start time).
class MRSKIN_BRIDGE_API Scene : public SlaveSource {
 public:
  [[nodiscard]] virtual std::string_view name() const noexcept = 0;
  // The mapping the scene was made with (the slave's tissue frame onto the skin).
  [[nodiscard]] virtual const WorkspaceMapping& mapping() const noexcept = 0;
  [[nodiscard]] virtual double cycle_s() const noexcept = 0;
  // The scene's true tissue law at a point of the slave's tissue frame. By value: the tumour
  // blends two laws across the inclusion's rim, so there is no stored model to refer to.
  [[nodiscard]] virtual TissueModel tissue_at(double x_m, double y_m) const noexcept = 0;
  [[nodiscard]] virtual SlaveTruth slave_truth(double t_s) const noexcept = 0;
  // Where the slave's contact maps on a rows x cols skin at scene time t_s (cell units), and its
  // depth, m: what a simulated finger presses to follow the slave (mrskin::eval::press_scene_finger).
  struct SkinContact {
    CellPoint at{};
    double depth_m = 0.0;
  };
  [[nodiscard]] SkinContact skin_contact(double t_s, int rows, int cols) const noexcept {
    const SlaveTruth s = slave_truth(t_s);
    return {mapping().to_cell(s.contact_x_m, s.contact_y_m, rows, cols), s.indentation_m};
  }
  void set_start(TimePoint t0) noexcept { start_ = t0; }
  [[nodiscard]] TimePoint start() const noexcept { return start_; }

 private:
  TimePoint start_{};
};

// ---- built-in scenes -------------------------------------------------------------------------
// Every scene's finger (on the mock: mrskin::eval::press_scene_finger) presses the skin where the
// mapping puts the slave's contact point, with the slave's indentation below the skin's rest.
// Workspace positions below are measured from the mapping's origin (the point rendered at the
// skin's centre); mirroring, rotation and scale then move the finger with the slave. Each
// cycle starts and ends out of contact and repeats; force stays in 0-2 N, depth in 0-5 mm.
// Except demo, the slave stream is sampled at 1 kHz (stamps on whole milliseconds from the
// start; no sample before it) with 5 mN RMS Gaussian force noise in contact (a fixed seed per
// scene; each sample's noise depends on its index alone); the tip radius is 3 mm.
//
// demo: a fingertip presses the centre of the skin, 0 -> 4 mm in 1 s, holds 1 s, releases in
//   1 s, rests 0.5 s, while the slave instrument palpates a stomach-like organ (Kelvin-Voigt,
//   300 N/m, 0.5 N s/m) at the mapping's origin with the same indentation profile, a sample at
//   every call (stamp = now), no noise. The fingertip touches the centre fluid cell only.
//
// hand, neck, abdomen, thigh, back, stomach: that organ preset (tissue.hpp) everywhere. The
//   slave palpates the origin lightly, then deeply: 0 -> the depth of the preset's lower force
//   in 0.8 s, hold 0.5 s, -> its reference depth in 0.5 s, hold 1 s, release in 1 s, rest
//   0.5 s (cycle 4.3 s). Light / deep holds: hand 0.6 N at 3.82 mm / 0.9 N at 5 mm, neck 0.6 at
//   3.15 / 1.2 at 5, abdomen 0.4 at 2.28 / 1.3 at 5, thigh 0.7 at 3.49 / 1.2 at 5, back 1.0 at
//   3.82 / 1.5 at 5 (paper Table 2's ranges); stomach (no lower force given: half the upper)
//   0.6 N at 2.73 mm / 1.2 N at 4 mm (the stomach curve).
//
// sweep: stomach_linear (Kelvin-Voigt 300 N/m, 0.5 N s/m) everywhere. Press in at (-20 mm, 0)
//   to 3 mm in 1 s, hold 0.5 s, slide to (+20 mm, 0) at a constant 10 mm/s (4 s), hold 0.5 s,
//   release in 1 s, return lifted in 0.5 s (cycle 7.5 s); 0.9 N while sliding. Default mapping
//   on the 5x5: the finger crosses the middle row from edge cell (2,0) to edge cell (2,4).
//
// tumour: soft abdomen tissue (Hertz, 1.3 N at 5 mm) with a hard inclusion centred at
//   (+10 mm, +10 mm): abdomen scaled by 4 within 5 mm of it, blending smoothly back to soft by
//   8 mm. The slave sweeps along y = +10 mm as in sweep (press in at x = -20 mm, slide to
//   +20 mm, same timing) at 2 mm depth: 0.33 N over soft tissue, 1.32 N over the inclusion.
//   Default mapping on the 5x5: along row 3, the inclusion under fluid cell (3,3).
//
// step: Hunt-Crossley tissue with n = 1 and heavy damping (k 100 N/m, lambda 4e4 N s/m^2) at the
//   origin. Press to 1.5 mm in 0.6 s, hold 0.4 s (0.15 N), then from a standstill at a constant
//   5 mm/s to 4.5 mm (0.6 s): the damping steps the force from 0.15 to 0.45 N at t = 1.0 s of
//   each cycle, then it rises to 1.35 N; hold 0.4 s (0.45 N: a step down, rendered as the
//   envelope allows), release in 1 s, rest 0.5 s (cycle 3.5 s). For settling measurements.
//
// force_step: Hunt-Crossley tissue with n = 1 (k 300 N/m, lambda 1.4e4 N s/m^2) at the origin,
//   two force steps of about 1 N a cycle (the settling figure, docs/bridge.md). Up: press to
//   1.5 mm in 0.6 s, hold 0.4 s (0.45 N), press on to 4.8 mm in 0.35 s and hold 0.6 s (1.44 N),
//   release in 0.6 s, rest 0.4 s. Down: press to 1 mm in 0.5 s, hold 0.3 s, press on at a
//   constant 25 mm/s to 2.9 mm (1.89 N as it arrives), stop there for 0.6 s (0.87 N: the damping's
//   1.0 N leaves at once), release in 0.6 s, rest (cycle 5.45 s). The slave's force peaks at
//   about 1.9 N in the up press.
//
// Names: scene_names(); "scene://NAME" is accepted too. Throws InvalidArgument (listing the
// names) for an unknown name, and for a mapping that is not valid().
MRSKIN_BRIDGE_API std::unique_ptr<Scene> make_scene(std::string_view name,
                                                    const WorkspaceMapping& mapping = {});
MRSKIN_BRIDGE_API std::span<const std::string_view> scene_names() noexcept;

}  // namespace mrskin::bridge
