// Tissue models for model-mediated rendering: the force laws, organ presets, online estimation
// from the slave's force/indentation stream, the stale-data policy, a passive rule for changing
// parameters during an indentation, and a time-domain passivity observer. docs/tissue.md.
//
// Real-time parts (every noexcept member) never allocate, lock, log or throw. Constructors that
// take options may throw mrskin::InvalidArgument.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string_view>

#include "mrskin/bridge/export.hpp"
#include "mrskin/driver/model/inverse.hpp"

namespace mrskin::bridge {

enum class TissueKind : unsigned char {
  kelvin_voigt,   // F = k x + b x'
  hunt_crossley,  // F = k x^n + lambda x^n x'
  hertz,          // Hunt-Crossley with n = 3/2 (sphere on a half-space)
  exponential,    // F = a (e^(beta x) - 1) + b x'
};
MRSKIN_BRIDGE_API const char* to_string(TissueKind kind) noexcept;

// A tissue law in the indentation x below the tissue's surface and its rate x'. Force is zero
// out of contact (x <= 0) and never negative: tissue cannot pull on the instrument.
struct MRSKIN_BRIDGE_API TissueModel {
  TissueKind kind = TissueKind::kelvin_voigt;
  double stiffness_N_per_m = 0.0;     // k; unit N/m^n for hunt_crossley and hertz
  double exponent = 1.0;              // n: 1 for kelvin_voigt, 1.5 for hertz
  double damping_N_s_per_m = 0.0;     // b (kelvin_voigt, exponential)
  double hc_damping_N_s_per_m = 0.0;  // lambda, unit N s/m^(n+1) (hunt_crossley, hertz)
  double exp_scale_N = 0.0;           // a (exponential)
  double exp_rate_per_m = 0.0;        // beta (exponential)

  static TissueModel kelvin_voigt(double k_N_per_m, double b_N_s_per_m) noexcept;
  static TissueModel hunt_crossley(double k_N_per_m_n, double n, double lambda_N_s_per_m_n1) noexcept;
  static TissueModel hertz(double k_N_per_m1_5, double lambda_N_s_per_m2_5) noexcept;
  // Hertz contact of a rigid sphere (radius) on an elastic half-space: k = 4/3 E/(1 - nu^2) sqrt(R).
  static TissueModel hertz_sphere(double youngs_modulus_Pa, double poisson_ratio, double radius_m,
                                  double lambda_N_s_per_m2_5) noexcept;
  static TissueModel exponential(double a_N, double beta_per_m, double b_N_s_per_m) noexcept;

  // All parameters finite and non-negative, exponent in [0.5, 4].
  [[nodiscard]] bool valid() const noexcept;
  // F(x, x') >= 0; 0 for x <= 0.
  [[nodiscard]] double force_N(double depth_m, double rate_m_per_s) const noexcept;
  // The elastic part alone (x' = 0).
  [[nodiscard]] double elastic_force_N(double depth_m) const noexcept;
  // Tangent dF/dx of the elastic part (at x <= 0: the limit from the right).
  [[nodiscard]] double tangent_stiffness_N_per_m(double depth_m) const noexcept;
  // Stored energy V(x) = integral_0^x of the elastic force, J.
  [[nodiscard]] double stored_energy_J(double depth_m) const noexcept;
  // Inverses of the (strictly increasing) elastic force and stored energy; 0 for inputs <= 0,
  // +inf when the law has no elastic part.
  [[nodiscard]] double depth_for_force_m(double force_N) const noexcept;
  [[nodiscard]] double depth_for_energy_m(double energy_J) const noexcept;
  // Every force term scaled by `scale` (the stale policy's fade).
  [[nodiscard]] TissueModel scaled(double scale) const noexcept;
  // The law through a change of units: F'(x, x') = force_scale F(x / length_scale, x' /
  // length_scale), exactly, for every kind (a unit of another design point: DesignScale).
  [[nodiscard]] TissueModel rescaled(double force_scale, double length_scale) const noexcept;
  // The inverse's law F = k x^n + b x' + lambda x^n x' with x = indentation - surface_offset_m.
  // Exact for kelvin_voigt, hunt_crossley and hertz. The exponential is replaced by the power law
  // tangent to it in log-log at the current depth x (same force and same tangent stiffness
  // there): n = beta x e^(beta x) / (e^(beta x) - 1) (>= 1, clamped to 4), k = F(x) / x^n; at
  // x -> 0 it is linear with k = a beta. Re-convert as the depth moves.
  [[nodiscard]] model::CellImpedanceTarget to_impedance_target(double depth_m, double surface_offset_m,
                                                               double force_ceiling_N,
                                                               double valid_until_s) const noexcept;
};

// ---- organ presets ---------------------------------------------------------------------------
struct TissuePreset {
  std::string_view name;
  TissueModel model;
  double force_min_N;  // the paper's palpation force range
  double force_max_N;
  double reference_depth_m;  // depth at which the preset renders force_max_N
  std::string_view source;
};
// Paper Table 2 (hand, neck, abdomen, thigh, back) and the stomach curve (stomach, and its
// linear secant stomach_linear). Derivations in tissue.cpp and docs/tissue.md.
MRSKIN_BRIDGE_API std::span<const TissuePreset> tissue_presets() noexcept;
MRSKIN_BRIDGE_API std::span<const std::string_view> preset_names() noexcept;
MRSKIN_BRIDGE_API const TissueModel* find_preset(std::string_view name) noexcept;  // nullptr when unknown
MRSKIN_BRIDGE_API const TissuePreset* find_tissue_preset(std::string_view name) noexcept;

// ---- online estimation -----------------------------------------------------------------------
// One slave sample. stamp_s is on the caller's clock (the same clock as estimate()'s now_s).
struct TissueSample {
  double stamp_s = 0.0;
  double force_N = 0.0;
  double indentation_m = 0.0;  // below the tissue's surface as the slave detected it
};

// Stale policy, on the age of the newest accepted sample (now_s - stamp_s):
//   no_data  nothing accepted yet: safe state;
//   fresh    age <= fresh_s: the estimate, scale 1;
//   holding  age <= hold_s: the last estimate held unchanged, scale 1;
//   fading   age <= hold_s + fade_s: every force term scaled by 1 - (age - hold_s) / fade_s;
//   safe     beyond: scale 0, zero force (valves released).
// A fresh sample restores scale 1 at once; PassiveTissueUpdate makes that rise passive.
enum class TissueFreshness : unsigned char { no_data, fresh, holding, fading, safe };
MRSKIN_BRIDGE_API const char* to_string(TissueFreshness f) noexcept;

struct TissueEstimatorOptions {
  TissueKind kind = TissueKind::hunt_crossley;  // the law to fit
  TissueModel prior{};                          // rendered until the fit is confident
  // The fit's memory, s: an in-contact sample's weight decays as exp(-age / memory_s), at any
  // stream rate (a factor per sample made the memory rate-bound: 0.995 kept 0.2 s at 1 kHz but 1 s
  // of a press at 200 Hz, where the law lagged a rising press by 0.3 N; docs/tissue.md). +inf: none.
  double memory_s = 0.2;
  // Regressors are normalised to these, so the fitted numbers are forces (N) of order one.
  double reference_depth_m = 5e-3;
  double reference_rate_m_per_s = 10e-3;
  // Low-pass applied alike to force and regressors (it cancels in the regression), s.
  double filter_s = 5e-3;
  double contact_depth_m = 0.1e-3;  // shallower samples are out of contact: no update
  double max_depth_m = 0.05;        // accepted |indentation|; beyond: rejected, counted
  double max_force_N = 50.0;
  double max_gap_s = 0.05;  // a longer gap restarts the differentiator
  // Exponent bank (hunt_crossley): bank_size values evenly in [exponent_min, exponent_max].
  double exponent_min = 1.0;
  double exponent_max = 2.5;
  // Rate bank (exponential): bank values log-spaced in [beta_min, beta_max], 1/m.
  double beta_min_per_m = 50.0;
  double beta_max_per_m = 1500.0;
  std::size_t bank_size = 16;  // 1..kMaxBank; kelvin_voigt and hertz use one
  // Parameter bounds, as forces at the reference depth (and rate): physically plausible ones.
  double max_elastic_force_at_ref_N = 20.0;
  double max_damping_force_at_ref_N = 5.0;
  double initial_covariance = 100.0;    // N^2
  double max_covariance_trace = 1.0e4;  // wind-up bound, N^2
  // Confidence = fit R^2 x min(1, contact time / min_contact_s) x min(1, depth std / min_depth_std_m),
  // the contact time forgotten as the fit is.
  double min_contact_s = 0.1;
  double min_depth_std_m = 0.3e-3;
  double min_confidence = 0.6;  // below: the last confident estimate (or the prior) is output
  double fresh_s = 0.02;
  double hold_s = 0.1;
  double fade_s = 0.2;
};

struct TissueEstimate {
  TissueModel model{};  // already scaled by the stale policy
  double confidence = 0.0;
  double scale = 0.0;  // stale policy's scale applied to model
  TissueFreshness freshness = TissueFreshness::no_data;
  bool fitted = false;  // false: prior (no confident fit yet)
  // When the fade reaches the safe state if no sample comes (newest stamp + hold_s + fade_s):
  // the CellImpedanceTarget::valid_until_s to send. 0 without data.
  double valid_until_s = 0.0;
};

struct TissueEstimatorStats {
  std::uint64_t accepted = 0;
  std::uint64_t rejected_non_finite = 0;
  std::uint64_t rejected_out_of_range = 0;
  std::uint64_t rejected_out_of_order = 0;  // stamp before the previous sample's
  std::uint64_t duplicates = 0;             // stamp equal to the previous one: ignored
  std::uint64_t updates = 0;                // in-contact regression updates
  std::uint64_t parameter_clamps = 0;       // selected fit projected into the bounds
  std::uint64_t covariance_limits = 0;      // covariance scaled back to max_covariance_trace
  std::uint64_t covariance_resets = 0;      // covariance lost definiteness: reset
  std::uint64_t gaps = 0;                   // differentiator restarts after max_gap_s
};

// Recursive least squares with forgetting on a bank of two-parameter linear regressions, one per
// candidate exponent (or exponential rate); the bank member with the smallest forgotten
// prediction error is the estimate. Hunt-Crossley is linear in (k, lambda) once n is fixed:
//   F = k x^n + lambda x^n x' = k x^n + lambda d/dt[x^(n+1) / (n+1)],
// so the damping regressor is the derivative of a known signal, taken as a difference quotient
// at the interval's midpoint (force and x^n averaged over the interval), and all three signals
// pass through the same low-pass. Out-of-contact samples refresh freshness but do not update.
class MRSKIN_BRIDGE_API TissueEstimator {
 public:
  static constexpr std::size_t kMaxBank = 32;
  explicit TissueEstimator(const TissueEstimatorOptions& options);  // throws InvalidArgument
  // Copies are deep (each has its own state); a moved-from estimator can only be assigned to or
  // destroyed.
  TissueEstimator(const TissueEstimator& other);
  TissueEstimator& operator=(const TissueEstimator& other);
  TissueEstimator(TissueEstimator&& other) noexcept;
  TissueEstimator& operator=(TissueEstimator&& other) noexcept;
  ~TissueEstimator();
  // false when the sample was rejected or repeats the previous stamp (counted in stats()); a
  // source that returns its newest sample every tick can push it every tick.
  bool push(const TissueSample& sample) noexcept;
  [[nodiscard]] TissueEstimate estimate(double now_s) const noexcept;
  // The stream's publisher went away at now_s (a DDS writer lost): the stale policy skips its
  // hold and fades from now_s. The next accepted sample ends it.
  void end_stream(double now_s) noexcept;
  // The current fit without stale scaling or confidence gating.
  [[nodiscard]] TissueModel raw_fit() const noexcept;
  [[nodiscard]] double confidence() const noexcept;
  [[nodiscard]] const TissueEstimatorStats& stats() const noexcept;
  [[nodiscard]] const TissueEstimatorOptions& options() const noexcept;
  // A new stale policy (hold, then fade) keeping the fit: setup only (between ticks). Throws
  // InvalidArgument unless fresh_s <= hold_s and fade_s > 0.
  void set_stale_policy(double hold_s, double fade_s);
  void reset() noexcept;

 private:
  // Everything else lives behind one pointer: a console linked against this header keeps its
  // ABI when the estimator's state changes (docs/api.md, "ABI").
  class Impl;
  std::unique_ptr<Impl> impl_;
};

// ---- passive parameter changes ---------------------------------------------------------------
// The rule for applying a new tissue law to a cell while the finger is in it. The rendered law is
// F_applied(x - o), o >= 0 a surface offset, V its stored energy. Energy the rule takes out of V
// goes into a small tank T (0 <= T <= tank_max_J, emptied when contact ends). A new law replaces
// the applied one at once with
//   o' = max(0, o_F, o_E),  F_new(x - o_F) = F_applied(x - o),  V_new(x - o_E) = V_applied(x - o) + T,
//   T' = min(tank_max_J, T + V_applied(x - o) - V_new(x - o')),
// so V + T never rises: what the finger can get back is bounded by what it put in (passive), and
// the force never jumps up. The force stays continuous when the new law is stiffer with the same
// shape (its offset rises) or when the tank covers a softer one; otherwise it drops. Without the
// tank, estimate noise (k up, k down, ...) would ratchet a held force down; with it it nets out.
// While the finger is above the shifted surface (x <= o) the offset follows it down (o = max(0,
// x)) at zero force and zero stored energy, so a full release restores the true surface. Damping
// terms change freely: they only dissipate. A law arriving while the applied one is zero (first
// contact, or after the stale fade) therefore starts from zero force at the current depth.
class MRSKIN_BRIDGE_API PassiveTissueUpdate {
 public:
  explicit PassiveTissueUpdate(double tank_max_J = 0.5e-3) noexcept
      : tank_max_J_(tank_max_J > 0.0 && tank_max_J < 1.0 ? tank_max_J : 0.0) {}
  // Per tick: the wanted law and the finger's indentation on this cell (below the skin's rest).
  // A non-finite indentation or an invalid law is ignored (the applied law stays).
  void update(const TissueModel& wanted, double indentation_m) noexcept;
  [[nodiscard]] const TissueModel& model() const noexcept { return applied_; }
  [[nodiscard]] double surface_offset_m() const noexcept { return offset_m_; }
  [[nodiscard]] double tank_J() const noexcept { return tank_J_; }
  [[nodiscard]] double force_N(double indentation_m, double rate_m_per_s) const noexcept;
  // The inverse's target for the applied law and offset (exponential: linearised at this depth).
  [[nodiscard]] model::CellImpedanceTarget target(double indentation_m, double force_ceiling_N,
                                                  double valid_until_s) const noexcept;
  [[nodiscard]] std::uint64_t changes() const noexcept { return changes_; }
  [[nodiscard]] std::uint64_t offset_raises() const noexcept { return offset_raises_; }
  [[nodiscard]] std::uint64_t force_drops() const noexcept { return force_drops_; }

 private:
  double tank_max_J_;
  TissueModel applied_{};
  double offset_m_ = 0.0;
  double tank_J_ = 0.0;
  std::uint64_t changes_ = 0;
  std::uint64_t offset_raises_ = 0;
  std::uint64_t force_drops_ = 0;
};

// ---- passivity observer ----------------------------------------------------------------------
// Plain figures for BridgeStats. energy_J is the energy that went into the rendered tissue,
// sum of F dx: a passive port keeps it >= 0.
struct PassivityStats {
  double energy_J = 0.0;
  double min_energy_J = 0.0;  // most negative value reached (0 if never)
  std::uint64_t samples = 0;
  std::uint64_t active_samples = 0;               // samples ending with energy_J < -tolerance
  std::uint64_t rejected_samples = 0;             // non-finite inputs, ignored
  double max_controller_damping_N_s_per_m = 0.0;  // largest damping controller_damping asked
};

// Totals over cells: energies and counts summed, min_energy_J the lowest of any cell (a cell's
// deficit is not offset by another cell's surplus), damping the largest.
MRSKIN_BRIDGE_API void accumulate(PassivityStats& total, const PassivityStats& cell) noexcept;

// Hannaford-Ryu time-domain passivity observer at one port: one fluid cell, force on the finger
// and the finger's indentation. Each sample adds the trapezoid (F_k + F_{k-1}) / 2 (x_k - x_{k-1}),
// which needs no rate estimate.
class MRSKIN_BRIDGE_API PassivityObserver {
 public:
  explicit PassivityObserver(double tolerance_J = 1e-6) noexcept : tolerance_J_(tolerance_J) {}
  void observe(double force_N, double indentation_m) noexcept;
  // Passivity controller: damping that, at this rate over dt, dissipates the current deficit
  // (0 while passive or nearly still), capped at max_N_s_per_m. Semi-active: it can only resist
  // loading or reduce force while unloading, which is what a deficit needs.
  [[nodiscard]] double controller_damping_N_s_per_m(double rate_m_per_s, double dt_s,
                                                    double max_N_s_per_m) noexcept;
  [[nodiscard]] const PassivityStats& stats() const noexcept { return stats_; }
  void reset() noexcept;

 private:
  double tolerance_J_;
  PassivityStats stats_{};
  bool primed_ = false;
  double last_force_N_ = 0.0;
  double last_indentation_m_ = 0.0;
};

}  // namespace mrskin::bridge
