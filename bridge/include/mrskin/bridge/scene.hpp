// Scripted scenes: a simulated finger on the skin and the slave robot's palpation stream,
// driven by one script so that every scene yields a measurable rendered-force error.
#pragma once

#include <memory>
#include <span>
#include <string_view>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/layout.hpp"

namespace mrskin::bridge {

// One slave-side sample: what the instrument feels.
struct SlaveSample {
  TimePoint stamp{};           // when the robot sampled it
  TimePoint received{};        // when it reached this host, on the loop's clock (0: at stamp)
  double force_N = 0.0;        // normal contact force on the tissue
  double indentation_m = 0.0;  // instrument indentation into the tissue
  double contact_row = 0.0;    // where on the skin to render it, in cell units
  double contact_col = 0.0;
  double contact_radius_cells = 0.0;
  bool valid = false;
};

// Produces the latest slave sample; called from the tick thread, never blocks.
class SlaveSource {
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

// A scene scripts both sides from t = 0 (its start time).
class Scene : public SlaveSource {
 public:
  [[nodiscard]] virtual std::string_view name() const noexcept = 0;
  // Finger indentation per fluid cell of layout at scene time t_s, m.
  virtual void finger(double t_s, const GridLayout& layout,
                      std::span<double> indentation_m) const noexcept = 0;
  [[nodiscard]] virtual double cycle_s() const noexcept = 0;
  void set_start(TimePoint t0) noexcept { start_ = t0; }
  [[nodiscard]] TimePoint start() const noexcept { return start_; }

 private:
  TimePoint start_{};
};

// scene://demo: a fingertip presses the centre of the skin, 0 -> 4 mm in 1 s, holds 1 s,
// releases in 1 s, rests 0.5 s, while the slave instrument palpates a stomach-like organ
// (Kelvin-Voigt, 300 N/m, 0.5 N s/m) with the same indentation profile. The fingertip
// (radius 1.2 cell pitches) touches the centre fluid cell only.
std::unique_ptr<Scene> make_scene(std::string_view name);  // throws InvalidArgument

}  // namespace mrskin::bridge
