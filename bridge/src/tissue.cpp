#include "mrskin/bridge/tissue.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <memory>
#include <string>
#include <type_traits>

#include "mrskin/driver/errors.hpp"

namespace mrskin::bridge {

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

bool finite(double v) noexcept { return std::isfinite(v); }

// x^n with the common n = 1 exact and cheap.
double pow_n(double x, double n) noexcept { return n == 1.0 ? x : std::pow(x, n); }

// integral_0^x (e^(beta s) - 1) ds, without the cancellation of expm1(bx)/b - x at small bx.
double exp_energy_unit(double beta, double x) noexcept {
  const double bx = beta * x;
  if (bx < 1e-4) {
    return x * bx * (0.5 + bx / 6.0);
  }
  return std::expm1(bx) / beta - x;
}

// Largest beta x evaluated: beyond it the exponential law is far outside any palpation.
constexpr double kMaxExpArgument = 50.0;

}  // namespace

const char* to_string(TissueKind kind) noexcept {
  switch (kind) {
    case TissueKind::kelvin_voigt:
      return "kelvin_voigt";
    case TissueKind::hunt_crossley:
      return "hunt_crossley";
    case TissueKind::hertz:
      return "hertz";
    case TissueKind::exponential:
      return "exponential";
  }
  return "unknown";
}

const char* to_string(TissueFreshness f) noexcept {
  switch (f) {
    case TissueFreshness::no_data:
      return "no_data";
    case TissueFreshness::fresh:
      return "fresh";
    case TissueFreshness::holding:
      return "holding";
    case TissueFreshness::fading:
      return "fading";
    case TissueFreshness::safe:
      return "safe";
  }
  return "unknown";
}

// ---- TissueModel -------------------------------------------------------------------------------

TissueModel TissueModel::kelvin_voigt(double k_N_per_m, double b_N_s_per_m) noexcept {
  return {.kind = TissueKind::kelvin_voigt, .stiffness_N_per_m = k_N_per_m, .damping_N_s_per_m = b_N_s_per_m};
}

TissueModel TissueModel::hunt_crossley(double k_N_per_m_n, double n, double lambda_N_s_per_m_n1) noexcept {
  return {.kind = TissueKind::hunt_crossley,
          .stiffness_N_per_m = k_N_per_m_n,
          .exponent = n,
          .hc_damping_N_s_per_m = lambda_N_s_per_m_n1};
}

TissueModel TissueModel::hertz(double k_N_per_m1_5, double lambda_N_s_per_m2_5) noexcept {
  return {.kind = TissueKind::hertz,
          .stiffness_N_per_m = k_N_per_m1_5,
          .exponent = 1.5,
          .hc_damping_N_s_per_m = lambda_N_s_per_m2_5};
}

TissueModel TissueModel::hertz_sphere(double youngs_modulus_Pa, double poisson_ratio, double radius_m,
                                      double lambda_N_s_per_m2_5) noexcept {
  const double e_star_Pa = youngs_modulus_Pa / (1.0 - poisson_ratio * poisson_ratio);
  return hertz(4.0 / 3.0 * e_star_Pa * std::sqrt(radius_m), lambda_N_s_per_m2_5);
}

TissueModel TissueModel::exponential(double a_N, double beta_per_m, double b_N_s_per_m) noexcept {
  return {.kind = TissueKind::exponential,
          .damping_N_s_per_m = b_N_s_per_m,
          .exp_scale_N = a_N,
          .exp_rate_per_m = beta_per_m};
}

bool TissueModel::valid() const noexcept {
  const double v[] = {stiffness_N_per_m, damping_N_s_per_m, hc_damping_N_s_per_m, exp_scale_N,
                      exp_rate_per_m};
  for (const double p : v) {
    if (!(p >= 0.0 && finite(p))) {
      return false;
    }
  }
  if (kind == TissueKind::kelvin_voigt && exponent != 1.0) {
    return false;
  }
  if (kind == TissueKind::hertz && exponent != 1.5) {
    return false;
  }
  return exponent >= 0.5 && exponent <= 4.0;
}

// Kelvin-Voigt is the power law with n = 1 (valid() enforces it), so the power-law branches serve
// all three power kinds.
double TissueModel::elastic_force_N(double depth_m) const noexcept {
  if (!(depth_m > 0.0)) {
    return 0.0;
  }
  if (kind == TissueKind::exponential) {
    return exp_scale_N * std::expm1(std::min(exp_rate_per_m * depth_m, kMaxExpArgument));
  }
  return stiffness_N_per_m * pow_n(depth_m, exponent);
}

// The inverse's law F = elastic + b x' + lambda x^n x' (b = 0 for the power laws but
// Kelvin-Voigt, lambda = 0 for Kelvin-Voigt and the exponential), never negative.
double TissueModel::force_N(double depth_m, double rate_m_per_s) const noexcept {
  if (!(depth_m > 0.0)) {
    return 0.0;
  }
  const double hc = hc_damping_N_s_per_m > 0.0 ? hc_damping_N_s_per_m * pow_n(depth_m, exponent) : 0.0;
  const double f = elastic_force_N(depth_m) + (damping_N_s_per_m + hc) * rate_m_per_s;
  return f > 0.0 ? f : 0.0;  // tissue cannot pull (also maps NaN to 0)
}

double TissueModel::tangent_stiffness_N_per_m(double depth_m) const noexcept {
  const double x = depth_m > 0.0 ? depth_m : 0.0;
  if (kind == TissueKind::exponential) {
    return exp_scale_N * exp_rate_per_m * std::exp(std::min(exp_rate_per_m * x, kMaxExpArgument));
  }
  if (exponent == 1.0) {
    return stiffness_N_per_m;
  }
  if (x > 0.0) {
    return exponent * stiffness_N_per_m * std::pow(x, exponent - 1.0);
  }
  return exponent > 1.0 ? 0.0 : kInf;
}

double TissueModel::stored_energy_J(double depth_m) const noexcept {
  if (!(depth_m > 0.0)) {
    return 0.0;
  }
  if (kind == TissueKind::exponential) {
    return exp_rate_per_m > 0.0
               ? exp_scale_N *
                     exp_energy_unit(exp_rate_per_m, std::min(depth_m, kMaxExpArgument / exp_rate_per_m))
               : 0.0;
  }
  return stiffness_N_per_m * std::pow(depth_m, exponent + 1.0) / (exponent + 1.0);
}

double TissueModel::depth_for_force_m(double force) const noexcept {
  if (!(force > 0.0)) {
    return 0.0;
  }
  if (kind == TissueKind::exponential) {
    return exp_scale_N > 0.0 && exp_rate_per_m > 0.0 ? std::log1p(force / exp_scale_N) / exp_rate_per_m
                                                     : kInf;
  }
  return stiffness_N_per_m > 0.0 ? std::pow(force / stiffness_N_per_m, 1.0 / exponent) : kInf;
}

double TissueModel::depth_for_energy_m(double energy_J) const noexcept {
  if (!(energy_J > 0.0)) {
    return 0.0;
  }
  if (kind != TissueKind::exponential) {
    return stiffness_N_per_m > 0.0
               ? std::pow((exponent + 1.0) * energy_J / stiffness_N_per_m, 1.0 / (exponent + 1.0))
               : kInf;
  }
  if (!(exp_scale_N > 0.0 && exp_rate_per_m > 0.0)) {
    return kInf;
  }
  // V is convex and increasing: Newton from above (V >= a beta s^2 / 2) descends monotonically.
  double s = std::sqrt(2.0 * energy_J / (exp_scale_N * exp_rate_per_m));
  for (int i = 0; i < 60; ++i) {
    const double f = stored_energy_J(s) - energy_J;
    const double df = elastic_force_N(s);
    if (!(df > 0.0) || !(f > 0.0)) {
      break;
    }
    const double next = s - f / df;
    if (!(next < s)) {
      break;
    }
    s = next;
  }
  return s;
}

TissueModel TissueModel::scaled(double scale) const noexcept {
  TissueModel m = *this;
  m.stiffness_N_per_m *= scale;
  m.damping_N_s_per_m *= scale;
  m.hc_damping_N_s_per_m *= scale;
  m.exp_scale_N *= scale;
  return m;
}

TissueModel TissueModel::rescaled(double force_scale, double length_scale) const noexcept {
  // F = elastic(x) + (b + lambda x^n) x': each term through x -> x / s, x' -> x' / s.
  TissueModel m = *this;
  const double per_length = 1.0 / length_scale;
  const double depth_factor = std::pow(per_length, exponent);  // x^n -> x^n / s^n
  m.damping_N_s_per_m *= force_scale * per_length;
  m.hc_damping_N_s_per_m *= force_scale * depth_factor * per_length;
  if (kind == TissueKind::exponential) {
    m.exp_scale_N *= force_scale;
    m.exp_rate_per_m *= per_length;
  } else {
    m.stiffness_N_per_m *= force_scale * depth_factor;  // k x^n
  }
  return m;
}

model::CellImpedanceTarget TissueModel::to_impedance_target(double depth_m, double surface_offset_m,
                                                            double force_ceiling_N,
                                                            double valid_until_s) const noexcept {
  model::CellImpedanceTarget t;
  t.surface_offset_m = surface_offset_m;
  t.force_ceiling_N = force_ceiling_N;
  t.valid_until_s = valid_until_s;
  switch (kind) {
    case TissueKind::kelvin_voigt:
      t.stiffness_N_per_m = stiffness_N_per_m;
      t.damping_N_s_per_m = damping_N_s_per_m;
      break;
    case TissueKind::hunt_crossley:
    case TissueKind::hertz:
      t.stiffness_N_per_m = stiffness_N_per_m;
      t.exponent = exponent;
      t.hc_damping_N_s_per_m2 = hc_damping_N_s_per_m;
      break;
    case TissueKind::exponential: {
      t.damping_N_s_per_m = damping_N_s_per_m;
      const double bx = exp_rate_per_m * (depth_m > 0.0 ? depth_m : 0.0);
      if (!(bx > 1e-6)) {
        t.stiffness_N_per_m = exp_scale_N * exp_rate_per_m;  // the linear limit at the surface
        break;
      }
      // Log-log tangent: n = x F'(x) / F(x), k = F(x) / x^n.
      const double n = std::min(bx / -std::expm1(-bx), 4.0);
      t.exponent = n;
      t.stiffness_N_per_m = elastic_force_N(depth_m) / std::pow(depth_m, n);
      break;
    }
  }
  return t;
}

// ---- presets -------------------------------------------------------------------------------------
//
// Paper (seed/000_7f5cb1f436bdd6a2.txt), Table 2 (Han et al.), palpation force per body part:
//   hand 0.6-0.9 N, neck 0.6-1.2 N, abdomen 0.4-1.3 N, thigh 0.7-1.2 N, back 1.0-1.5 N.
// The table gives forces only. The paper maps the top of that range (1.5 N) onto its design
// indentation of 5 mm ("to satisfy the design requirements, a displacement value of 0.005 m was
// chosen"), so each organ renders its upper force at 5 mm. Skin over soft tissue under a
// fingertip-sized probe is a Hertz contact: F = k x^1.5, k = F_max / (5 mm)^1.5. Damping is not in
// the paper: Hunt-Crossley lambda = 3 s/m x k (3 % of the elastic force at 10 mm/s; assumed).
// Stomach (Ogawa et al., paper Fig. 6): about 1.2 N at 4 mm, secant 300 N/m. Soft organs stiffen
// with depth: exponential a (e^(beta x) - 1) with beta = 400 /m (assumed: the curve itself is not
// in the text) and a = 1.2 N / (e^1.6 - 1) = 0.3036 N, so F(4 mm) = 1.2 N exactly, F(5 mm) = 1.94 N
// (inside the device's 2 N); stomach_linear is the secant Kelvin-Voigt 300 N/m. Their damping
// 0.5 N s/m is the demo scene's (assumed).
namespace {

constexpr double kTable2Depth_m = 5e-3;
constexpr double kHcDampingRatio_s_per_m = 3.0;
constexpr double kStomachDepth_m = 4e-3;
constexpr double kStomachForce_N = 1.2;
constexpr double kStomachBeta_per_m = 400.0;
constexpr double kStomachDamping_N_s_per_m = 0.5;

TissuePreset table2(std::string_view name, double lo_N, double hi_N) noexcept {
  const double k = hi_N / std::pow(kTable2Depth_m, 1.5);
  return TissuePreset{
      name,           TissueModel::hertz(k, kHcDampingRatio_s_per_m * k),
      lo_N,           hi_N,
      kTable2Depth_m, "paper Table 2 (Han et al.): upper force at the 5 mm design indentation, Hertz"};
}

const std::array<TissuePreset, 7>& presets() noexcept {
  static const std::array<TissuePreset, 7> table = {
      table2("hand", 0.6, 0.9),
      table2("neck", 0.6, 1.2),
      table2("abdomen", 0.4, 1.3),
      table2("thigh", 0.7, 1.2),
      table2("back", 1.0, 1.5),
      TissuePreset{
          "stomach",
          TissueModel::exponential(kStomachForce_N / std::expm1(kStomachBeta_per_m * kStomachDepth_m),
                                   kStomachBeta_per_m, kStomachDamping_N_s_per_m),
          0.0, kStomachForce_N, kStomachDepth_m,
          "paper Fig. 6 (Ogawa et al.): 1.2 N at 4 mm, exponential with beta 400 /m"},
      TissuePreset{"stomach_linear",
                   TissueModel::kelvin_voigt(kStomachForce_N / kStomachDepth_m, kStomachDamping_N_s_per_m),
                   0.0, kStomachForce_N, kStomachDepth_m, "paper Fig. 6 (Ogawa et al.): secant 300 N/m"},
  };
  return table;
}

constexpr std::array<std::string_view, 7> kPresetNames = {"hand", "neck",    "abdomen",       "thigh",
                                                          "back", "stomach", "stomach_linear"};

}  // namespace

std::span<const TissuePreset> tissue_presets() noexcept { return presets(); }

std::span<const std::string_view> preset_names() noexcept { return kPresetNames; }

const TissuePreset* find_tissue_preset(std::string_view name) noexcept {
  for (const TissuePreset& p : presets()) {
    if (p.name == name) {
      return &p;
    }
  }
  return nullptr;
}

const TissueModel* find_preset(std::string_view name) noexcept {
  const TissuePreset* p = find_tissue_preset(name);
  return p == nullptr ? nullptr : &p->model;
}

// ---- estimator -----------------------------------------------------------------------------------

namespace {

void require(bool ok, const std::string& what) {
  if (!ok) {
    throw InvalidArgument("tissue estimator: " + what);
  }
}

}  // namespace

// The estimator's state, behind TissueEstimator's one pointer (docs/api.md, "ABI").
class __attribute__((visibility("hidden"))) TissueEstimator::Impl {
 public:
  explicit Impl(const TissueEstimatorOptions& options);
  bool push(const TissueSample& sample) noexcept;
  [[nodiscard]] TissueEstimate estimate(double now_s) const noexcept;
  void end_stream(double now_s) noexcept;
  [[nodiscard]] TissueModel raw_fit() const noexcept;
  [[nodiscard]] double confidence() const noexcept;
  [[nodiscard]] const TissueEstimatorStats& stats() const noexcept { return stats_; }
  [[nodiscard]] const TissueEstimatorOptions& options() const noexcept { return options_; }
  void set_stale_policy(double hold_s, double fade_s);
  void reset() noexcept;

 private:
  // A member's law: its shape (n, or beta in 1/m) and its fit (forces at the reference).
  struct Member {
    double shape = 1.0;
    std::array<double, 2> theta{};
  };
  // The bank as a structure of arrays, one entry per member: push() updates every member in one
  // pass the compiler vectorises, then takes the rare resets member by member.
  struct Bank {
    std::array<double, kMaxBank> shape{};
    std::array<double, kMaxBank> theta0{};
    std::array<double, kMaxBank> theta1{};
    std::array<double, kMaxBank> p0{};  // covariance, symmetric 2x2: p0 p1 / p2 p3
    std::array<double, kMaxBank> p1{};
    std::array<double, kMaxBank> p2{};
    std::array<double, kMaxBank> p3{};
    std::array<double, kMaxBank> phi1_f{};  // filtered regressors
    std::array<double, kMaxBank> phi2_f{};
    std::array<double, kMaxBank> g1_prev{};  // elastic regressor at the previous sample
    std::array<double, kMaxBank> g2_prev{};  // antiderivative behind the damping regressor
    std::array<double, kMaxBank> err2{};     // forgotten sum of squared prediction errors
  };
  // Each member's candidate step (update_bank's first pass), applied or refused by its second.
  struct Step {
    std::array<double, kMaxBank> s{};
    std::array<double, kMaxBank> e{};
    std::array<double, kMaxBank> err2{};
    std::array<double, kMaxBank> theta0{};
    std::array<double, kMaxBank> theta1{};
    std::array<double, kMaxBank> p0{};
    std::array<double, kMaxBank> off{};
    std::array<double, kMaxBank> p3{};
  };
  [[nodiscard]] Member member(std::size_t j) const noexcept {
    return Member{bank_.shape[j], {bank_.theta0[j], bank_.theta1[j]}};
  }
  void reset_covariance(std::size_t j) noexcept {
    bank_.p0[j] = options_.initial_covariance;
    bank_.p1[j] = 0.0;
    bank_.p2[j] = 0.0;
    bank_.p3[j] = options_.initial_covariance;
  }
  void regressors(double shape, double xs, double& g1, double& g2) const noexcept;
  // push()'s steps, defined inline below (its only caller): a sample admitted, each member's
  // least squares step, then the moments, the best member and the confident law.
  inline bool admit(const TissueSample& sample) noexcept;
  inline void update_bank(double alpha, double d2) noexcept;
  inline void update_fit(double indentation_m, double dt) noexcept;
  // Every member's regressors at xs into g1_/g2_: the Hunt-Crossley bank's exponents are evenly
  // spaced, so x^n climbs by one factor x^dn per member (two pow calls, not one each).
  void bank_regressors(double xs) noexcept;
  [[nodiscard]] TissueModel to_model(const Member& m) const noexcept;
  void restart_pair(double xs) noexcept;

  bool stream_ended_ = false;
  double ended_at_s_ = 0.0;
  TissueEstimatorOptions options_;
  Bank bank_{};
  Step step_{};
  std::array<double, kMaxBank> g1_{};
  std::array<double, kMaxBank> g2_{};
  std::size_t bank_size_ = 1;
  std::size_t best_ = 0;
  TissueEstimatorStats stats_{};
  bool have_sample_ = false;
  bool have_pair_ = false;  // previous sample in contact and recent: differences are valid
  bool filter_primed_ = false;
  bool confident_ = false;
  double last_stamp_s_ = 0.0;
  double last_force_N_ = 0.0;
  double force_f_ = 0.0;
  // Forgotten moments of the filtered force and of the depth (for R^2 and excitation).
  double weight_ = 0.0;
  double contact_s_ = 0.0;  // in-contact time, forgotten alike
  // This sample's forgetting factor exp(-dt / memory_s), kept for the interval it was made for.
  double mu_ = 1.0;
  double mu_dt_s_ = -1.0;
  double force_sum_ = 0.0;
  double force_sq_sum_ = 0.0;
  double depth_sum_ = 0.0;
  double depth_sq_sum_ = 0.0;
  TissueModel last_good_{};
};

TissueEstimator::Impl::Impl(const TissueEstimatorOptions& options) : options_(options) {
  const TissueEstimatorOptions& o = options_;
  require(o.memory_s >= 1e-3, "memory_s must be >= 1e-3 s (0.2 s by default; +inf forgets nothing)");
  require(o.reference_depth_m > 0.0 && finite(o.reference_depth_m),
          "reference_depth_m must be > 0 (a typical palpation depth, e.g. 5e-3)");
  require(o.reference_rate_m_per_s > 0.0 && finite(o.reference_rate_m_per_s),
          "reference_rate_m_per_s must be > 0 (a typical indentation rate, e.g. 10e-3)");
  require(o.filter_s >= 0.0 && finite(o.filter_s), "filter_s must be >= 0 (0 disables the low-pass)");
  require(o.contact_depth_m >= 0.0 && o.max_depth_m > o.contact_depth_m && finite(o.max_depth_m),
          "need 0 <= contact_depth_m < max_depth_m");
  require(o.max_force_N > 0.0 && finite(o.max_force_N), "max_force_N must be > 0");
  require(o.max_gap_s > 0.0, "max_gap_s must be > 0 (e.g. 0.05)");
  require(o.exponent_min >= 0.5 && o.exponent_max <= 4.0 && o.exponent_min <= o.exponent_max,
          "exponents must satisfy 0.5 <= exponent_min <= exponent_max <= 4");
  require(o.beta_min_per_m > 0.0 && o.beta_max_per_m >= o.beta_min_per_m && finite(o.beta_max_per_m),
          "need 0 < beta_min_per_m <= beta_max_per_m");
  require(o.bank_size >= 1 && o.bank_size <= kMaxBank, "bank_size must be in 1.." + std::to_string(kMaxBank));
  require(o.max_elastic_force_at_ref_N > 0.0 && o.max_damping_force_at_ref_N >= 0.0,
          "parameter bounds must be positive (forces at the reference depth and rate, N)");
  require(o.initial_covariance > 0.0 && o.max_covariance_trace >= 2.0 * o.initial_covariance,
          "need initial_covariance > 0 and max_covariance_trace >= 2 x initial_covariance");
  require(o.min_contact_s > 0.0 && finite(o.min_contact_s) && o.min_depth_std_m >= 0.0 &&
              o.min_confidence >= 0.0 && o.min_confidence <= 1.0,
          "need min_contact_s > 0, min_depth_std_m >= 0 and min_confidence in [0, 1]");
  require(o.fresh_s >= 0.0 && o.hold_s >= o.fresh_s && o.fade_s > 0.0,
          "stale policy needs 0 <= fresh_s <= hold_s and fade_s > 0");
  require(o.prior.valid(), "the prior tissue model has a negative, non-finite or out-of-range parameter");
  switch (o.kind) {
    case TissueKind::kelvin_voigt:
    case TissueKind::hertz:
      bank_size_ = 1;
      break;
    case TissueKind::hunt_crossley:
    case TissueKind::exponential:
      bank_size_ = o.bank_size;
      break;
  }
  reset();
}

void TissueEstimator::Impl::set_stale_policy(double hold_s, double fade_s) {
  if (!(hold_s >= options_.fresh_s && std::isfinite(hold_s) && fade_s > 0.0 && std::isfinite(fade_s))) {
    throw InvalidArgument("stale policy needs fresh_s <= hold_s and fade_s > 0 (finite, seconds)");
  }
  options_.hold_s = hold_s;
  options_.fade_s = fade_s;
}

void TissueEstimator::Impl::reset() noexcept {
  const TissueEstimatorOptions& o = options_;
  const double xr = o.reference_depth_m;
  const double vr = o.reference_rate_m_per_s;
  // The prior as forces at the reference depth and rate: a start shared by every member.
  const double theta1 = std::clamp(o.prior.elastic_force_N(xr), 0.0, o.max_elastic_force_at_ref_N);
  const double theta2 =
      std::clamp(o.prior.force_N(xr, vr) - o.prior.elastic_force_N(xr), 0.0, o.max_damping_force_at_ref_N);
  bank_ = Bank{};
  for (std::size_t j = 0; j < bank_size_; ++j) {
    const double f = bank_size_ > 1 ? static_cast<double>(j) / static_cast<double>(bank_size_ - 1) : 0.0;
    double& shape = bank_.shape[j];
    switch (o.kind) {
      case TissueKind::kelvin_voigt:
        shape = 1.0;
        break;
      case TissueKind::hertz:
        shape = 1.5;
        break;
      case TissueKind::hunt_crossley:
        shape = o.exponent_min + f * (o.exponent_max - o.exponent_min);
        break;
      case TissueKind::exponential:
        shape = o.beta_min_per_m * std::pow(o.beta_max_per_m / o.beta_min_per_m, f);
        break;
    }
    bank_.theta0[j] = theta1;
    bank_.theta1[j] = theta2;
    reset_covariance(j);
  }
  best_ = 0;
  stats_ = {};
  have_sample_ = false;
  stream_ended_ = false;
  have_pair_ = false;
  filter_primed_ = false;
  confident_ = false;
  last_stamp_s_ = 0.0;
  last_force_N_ = 0.0;
  force_f_ = 0.0;
  weight_ = contact_s_ = force_sum_ = force_sq_sum_ = depth_sum_ = depth_sq_sum_ = 0.0;
  last_good_ = o.prior;
}

// g1: the elastic regressor at normalised depth xs; g2: the signal whose time derivative (times
// x_ref / v_ref) is the damping regressor.
void TissueEstimator::Impl::regressors(double shape, double xs, double& g1, double& g2) const noexcept {
  switch (options_.kind) {
    case TissueKind::kelvin_voigt:
      g1 = xs;
      g2 = xs;
      return;
    case TissueKind::hunt_crossley:
    case TissueKind::hertz: {
      g1 = pow_n(xs, shape);
      g2 = g1 * xs / (shape + 1.0);
      return;
    }
    case TissueKind::exponential: {
      const double xr = options_.reference_depth_m;
      g1 = std::expm1(std::min(shape * xs * xr, kMaxExpArgument)) / std::expm1(shape * xr);
      g2 = xs;
      return;
    }
  }
}

TissueModel TissueEstimator::Impl::to_model(const Member& member) const noexcept {
  const double xr = options_.reference_depth_m;
  const double vr = options_.reference_rate_m_per_s;
  // The regression runs unconstrained (a projected RLS estimate is no longer the least-squares
  // fit: on the demo's clean Kelvin-Voigt press, lambda clamped at 0 drove k from 300 to 6e6 N/m
  // within 0.1 s); the law it yields is projected onto the plausible box (tissue stiffness and
  // damping are not negative).
  Member m = member;
  m.theta = {std::clamp(m.theta[0], 0.0, options_.max_elastic_force_at_ref_N),
             std::clamp(m.theta[1], 0.0, options_.max_damping_force_at_ref_N)};
  switch (options_.kind) {
    case TissueKind::kelvin_voigt:
      return TissueModel::kelvin_voigt(m.theta[0] / xr, m.theta[1] / vr);
    case TissueKind::hunt_crossley:
    case TissueKind::hertz: {
      const double xrn = std::pow(xr, m.shape);
      TissueModel t = TissueModel::hunt_crossley(m.theta[0] / xrn, m.shape, m.theta[1] / (xrn * vr));
      t.kind = options_.kind;
      return t;
    }
    case TissueKind::exponential:
      return TissueModel::exponential(m.theta[0] / std::expm1(m.shape * xr), m.shape, m.theta[1] / vr);
  }
  return {};
}

void TissueEstimator::Impl::bank_regressors(double xs) noexcept {
  if (options_.kind == TissueKind::hunt_crossley && bank_size_ > 1) {
    double g1 = pow_n(xs, bank_.shape[0]);
    const double factor = std::pow(xs, bank_.shape[1] - bank_.shape[0]);
    for (std::size_t j = 0; j < bank_size_; ++j) {
      g1_[j] = g1;
      g2_[j] = g1 * xs / (bank_.shape[j] + 1.0);
      g1 *= factor;
    }
    return;
  }
  for (std::size_t j = 0; j < bank_size_; ++j) {
    regressors(bank_.shape[j], xs, g1_[j], g2_[j]);
  }
}

void TissueEstimator::Impl::restart_pair(double xs) noexcept {
  bank_regressors(xs);
  for (std::size_t j = 0; j < bank_size_; ++j) {
    bank_.g1_prev[j] = g1_[j];
    bank_.g2_prev[j] = g2_[j];
  }
  have_pair_ = true;
  filter_primed_ = false;
}

// Refuses (and counts) a sample that is not finite, out of range, a duplicate or out of order.
inline bool TissueEstimator::Impl::admit(const TissueSample& sample) noexcept {
  const TissueEstimatorOptions& o = options_;
  if (!finite(sample.stamp_s) || !finite(sample.force_N) || !finite(sample.indentation_m)) {
    ++stats_.rejected_non_finite;
    return false;
  }
  if (std::fabs(sample.indentation_m) > o.max_depth_m || std::fabs(sample.force_N) > o.max_force_N) {
    ++stats_.rejected_out_of_range;
    return false;
  }
  if (have_sample_ && sample.stamp_s == last_stamp_s_) {
    ++stats_.duplicates;
    return false;
  }
  if (have_sample_ && sample.stamp_s < last_stamp_s_) {
    ++stats_.rejected_out_of_order;
    return false;
  }
  return true;
}

// Every bank member's recursive least squares step on this sample's filtered regressors, as one
// member's step at a time would take it: a first pass computes each member's candidate step
// without a branch (the compiler vectorises it), a second applies it or takes the member's rare
// reset (a covariance that lost definiteness, a non-finite value) or its cap.
inline void TissueEstimator::Impl::update_bank(double alpha, double d2) noexcept {
  const TissueEstimatorOptions& o = options_;
  const double mu = mu_;
  const double force_f = force_f_;
  const std::size_t n = bank_size_;
  Bank& b = bank_;
  Step& t = step_;
  // (The filter's first sample is taken as it is: a loop of its own, so that neither branches.)
  const auto first_pass = [&](auto primed_constant) {
    constexpr bool kPrimed = decltype(primed_constant)::value;
    for (std::size_t j = 0; j < n; ++j) {
      const double g1 = g1_[j];
      const double g2 = g2_[j];
      const double phi1 = 0.5 * (g1 + b.g1_prev[j]);
      const double phi2 = (g2 - b.g2_prev[j]) * d2;
      b.g1_prev[j] = g1;
      b.g2_prev[j] = g2;
      const double p1 = kPrimed ? b.phi1_f[j] + alpha * (phi1 - b.phi1_f[j]) : phi1;
      const double p2 = kPrimed ? b.phi2_f[j] + alpha * (phi2 - b.phi2_f[j]) : phi2;
      b.phi1_f[j] = p1;
      b.phi2_f[j] = p2;
      const double pp0 = b.p0[j] * p1 + b.p1[j] * p2;
      const double pp1 = b.p2[j] * p1 + b.p3[j] * p2;
      const double s = mu + p1 * pp0 + p2 * pp1;
      const double e = force_f - (b.theta0[j] * p1 + b.theta1[j] * p2);
      // A-posteriori error e mu / s: the fit after this sample (early prior mismatch fades fast).
      const double e_post = e * mu / s;
      const double k0 = pp0 / s;
      const double k1 = pp1 / s;
      t.s[j] = s;
      t.e[j] = e;
      t.err2[j] = mu * b.err2[j] + e_post * e_post;
      t.theta0[j] = b.theta0[j] + k0 * e;
      t.theta1[j] = b.theta1[j] + k1 * e;
      t.off[j] = 0.5 * ((b.p1[j] - k0 * pp1) + (b.p2[j] - k1 * pp0)) / mu;
      t.p0[j] = (b.p0[j] - k0 * pp0) / mu;
      t.p3[j] = (b.p3[j] - k1 * pp1) / mu;
    }
  };
  if (filter_primed_) {
    first_pass(std::true_type{});
  } else {
    first_pass(std::false_type{});
  }
  for (std::size_t j = 0; j < n; ++j) {
    const double s = t.s[j];
    const double e = t.e[j];
    if (!(s > 0.0) || !finite(s) || !finite(e)) {
      b.err2[j] = mu * b.err2[j] + (finite(e) ? e * e : 0.0);
      ++stats_.covariance_resets;
      reset_covariance(j);
      continue;
    }
    b.err2[j] = t.err2[j];
    b.theta0[j] = t.theta0[j];
    b.theta1[j] = t.theta1[j];
    const double p0 = t.p0[j];
    const double off = t.off[j];
    const double p3 = t.p3[j];
    if (!(p0 > 0.0 && p3 > 0.0 && p0 * p3 - off * off > 0.0) || !finite(p0 + p3)) {
      ++stats_.covariance_resets;
      reset_covariance(j);
    } else if (const double tr = p0 + p3; tr > o.max_covariance_trace) {
      // Forgetting without excitation blows the covariance up (wind-up): cap it.
      const double c = o.max_covariance_trace / tr;
      b.p0[j] = p0 * c;
      b.p1[j] = off * c;
      b.p2[j] = off * c;
      b.p3[j] = p3 * c;
      if (j == best_) {
        ++stats_.covariance_limits;
      }
    } else {
      b.p0[j] = p0;
      b.p1[j] = off;
      b.p2[j] = off;
      b.p3[j] = p3;
    }
    if (!finite(b.theta0[j]) || !finite(b.theta1[j])) {
      b.theta0[j] = 0.0;
      b.theta1[j] = 0.0;
      ++stats_.covariance_resets;
      reset_covariance(j);
    }
  }
}

// The forgotten moments of force and depth, the best member (smallest forgotten prediction error,
// with 2 % hysteresis against flicker between neighbours), and the law once it is confident.
inline void TissueEstimator::Impl::update_fit(double indentation_m, double dt) noexcept {
  const TissueEstimatorOptions& o = options_;
  const double mu = mu_;
  weight_ = mu * weight_ + 1.0;
  contact_s_ = mu * contact_s_ + dt;
  force_sum_ = mu * force_sum_ + force_f_;
  force_sq_sum_ = mu * force_sq_sum_ + force_f_ * force_f_;
  depth_sum_ = mu * depth_sum_ + indentation_m;
  depth_sq_sum_ = mu * depth_sq_sum_ + indentation_m * indentation_m;
  std::size_t best = best_;
  for (std::size_t j = 0; j < bank_size_; ++j) {
    if (bank_.err2[j] < bank_.err2[best]) {
      best = j;
    }
  }
  if (bank_.err2[best] < 0.98 * bank_.err2[best_]) {
    best_ = best;
  }
  const std::array<double, 2> fit = {bank_.theta0[best_], bank_.theta1[best_]};
  if (fit[0] < 0.0 || fit[0] > o.max_elastic_force_at_ref_N || fit[1] < 0.0 ||
      fit[1] > o.max_damping_force_at_ref_N) {
    ++stats_.parameter_clamps;  // the law is projected onto the plausible box
  }
  if (confidence() >= o.min_confidence) {
    last_good_ = to_model(member(best_));
    confident_ = true;
  }
}

bool TissueEstimator::Impl::push(const TissueSample& sample) noexcept {
  if (!admit(sample)) {
    return false;
  }
  const TissueEstimatorOptions& o = options_;
  ++stats_.accepted;
  const double dt = sample.stamp_s - last_stamp_s_;
  const bool was_sample = have_sample_;
  have_sample_ = true;
  stream_ended_ = false;
  last_stamp_s_ = sample.stamp_s;
  const double f_prev = last_force_N_;
  last_force_N_ = sample.force_N;
  const double xs = sample.indentation_m / o.reference_depth_m;
  if (!(sample.indentation_m > o.contact_depth_m)) {
    have_pair_ = false;  // out of contact: nothing to learn about the tissue
    return true;
  }
  if (!have_pair_ || !was_sample || dt > o.max_gap_s) {
    if (have_pair_ && dt > o.max_gap_s) {
      ++stats_.gaps;
    }
    restart_pair(xs);
    return true;
  }
  const double alpha = o.filter_s > 0.0 ? dt / (o.filter_s + dt) : 1.0;
  const double d2 = o.reference_depth_m / (o.reference_rate_m_per_s * dt);
  const double force_mid = 0.5 * (sample.force_N + f_prev);
  force_f_ = filter_primed_ ? force_f_ + alpha * (force_mid - force_f_) : force_mid;
  // A stream at a steady rate pays for one exp (its intervals differ in their last bits).
  if (std::abs(dt - mu_dt_s_) > 1e-9 * dt) {
    mu_dt_s_ = dt;
    mu_ = std::exp(-dt / o.memory_s);
  }
  bank_regressors(xs);
  update_bank(alpha, d2);
  filter_primed_ = true;
  ++stats_.updates;
  update_fit(sample.indentation_m, dt);
  return true;
}

double TissueEstimator::Impl::confidence() const noexcept {
  if (!(weight_ > 0.0)) {
    return 0.0;
  }
  const double var_sum = force_sq_sum_ - force_sum_ * force_sum_ / weight_;
  const double r2 = var_sum > 1e-12 ? std::clamp(1.0 - bank_.err2[best_] / var_sum, 0.0, 1.0) : 0.0;
  const double mean = depth_sum_ / weight_;
  const double depth_std = std::sqrt(std::max(0.0, depth_sq_sum_ / weight_ - mean * mean));
  const double excitation =
      options_.min_depth_std_m > 0.0 ? std::min(1.0, depth_std / options_.min_depth_std_m) : 1.0;
  const double amount = std::min(1.0, contact_s_ / options_.min_contact_s);
  const double c = r2 * excitation * amount;
  return finite(c) ? c : 0.0;
}

void TissueEstimator::Impl::end_stream(double now_s) noexcept {
  if (have_sample_ && !stream_ended_ && finite(now_s)) {
    stream_ended_ = true;
    ended_at_s_ = now_s;
  }
}

TissueModel TissueEstimator::Impl::raw_fit() const noexcept { return to_model(member(best_)); }

TissueEstimate TissueEstimator::Impl::estimate(double now_s) const noexcept {
  TissueEstimate out;
  out.confidence = confidence();
  out.fitted = confident_;
  const TissueEstimatorOptions& o = options_;
  if (!have_sample_) {
    out.freshness = TissueFreshness::no_data;
    out.model = last_good_.scaled(0.0);
    return out;
  }
  out.valid_until_s = stream_ended_ ? ended_at_s_ + o.fade_s : last_stamp_s_ + o.hold_s + o.fade_s;
  // A non-finite clock reads as very old: safe. An ended stream is past its hold at once.
  double age_s = finite(now_s) ? std::max(0.0, now_s - last_stamp_s_) : std::numeric_limits<double>::max();
  if (stream_ended_) {
    age_s = std::max(age_s, o.hold_s + std::max(0.0, now_s - ended_at_s_));
  }
  if (age_s <= o.fresh_s) {
    out.freshness = TissueFreshness::fresh;
    out.scale = 1.0;
  } else if (age_s <= o.hold_s) {
    out.freshness = TissueFreshness::holding;
    out.scale = 1.0;
  } else if (age_s < o.hold_s + o.fade_s) {
    out.freshness = TissueFreshness::fading;
    out.scale = 1.0 - (age_s - o.hold_s) / o.fade_s;
  } else {
    out.freshness = TissueFreshness::safe;
    out.scale = 0.0;
  }
  out.model = last_good_.scaled(out.scale);
  return out;
}

// ---- TissueEstimator: the public face, one pointer to the state ----------------------------

TissueEstimator::TissueEstimator(const TissueEstimatorOptions& options)
    : impl_(std::make_unique<Impl>(options)) {}
TissueEstimator::TissueEstimator(const TissueEstimator& other)
    : impl_(std::make_unique<Impl>(*other.impl_)) {}
TissueEstimator& TissueEstimator::operator=(const TissueEstimator& other) {
  return *this = TissueEstimator(other);
}
TissueEstimator::TissueEstimator(TissueEstimator&&) noexcept = default;
TissueEstimator& TissueEstimator::operator=(TissueEstimator&&) noexcept = default;
TissueEstimator::~TissueEstimator() = default;
bool TissueEstimator::push(const TissueSample& sample) noexcept { return impl_->push(sample); }
TissueEstimate TissueEstimator::estimate(double now_s) const noexcept { return impl_->estimate(now_s); }
void TissueEstimator::end_stream(double now_s) noexcept { impl_->end_stream(now_s); }
TissueModel TissueEstimator::raw_fit() const noexcept { return impl_->raw_fit(); }
double TissueEstimator::confidence() const noexcept { return impl_->confidence(); }
const TissueEstimatorStats& TissueEstimator::stats() const noexcept { return impl_->stats(); }
const TissueEstimatorOptions& TissueEstimator::options() const noexcept { return impl_->options(); }
void TissueEstimator::set_stale_policy(double hold_s, double fade_s) {
  impl_->set_stale_policy(hold_s, fade_s);
}
void TissueEstimator::reset() noexcept { impl_->reset(); }

static_assert(sizeof(TissueEstimator) == sizeof(void*),
              "TissueEstimator is one pointer: its state lives in TissueEstimator::Impl");

// ---- passive parameter changes -------------------------------------------------------------------

namespace {

bool same_law(const TissueModel& a, const TissueModel& b) noexcept {
  return a.kind == b.kind && a.stiffness_N_per_m == b.stiffness_N_per_m && a.exponent == b.exponent &&
         a.damping_N_s_per_m == b.damping_N_s_per_m && a.hc_damping_N_s_per_m == b.hc_damping_N_s_per_m &&
         a.exp_scale_N == b.exp_scale_N && a.exp_rate_per_m == b.exp_rate_per_m;
}

}  // namespace

void PassiveTissueUpdate::update(const TissueModel& wanted, double indentation_m) noexcept {
  if (!finite(indentation_m) || !wanted.valid()) {
    return;  // keep the applied law: never render garbage
  }
  if (!(indentation_m > offset_m_)) {
    offset_m_ = std::max(0.0, indentation_m);  // above the shifted surface: follow the finger down
    tank_J_ = 0.0;                             // V = 0: this indentation is over
  }
  if (same_law(wanted, applied_)) {
    return;
  }
  ++changes_;
  const double x = indentation_m - offset_m_;
  if (!(x > 0.0)) {
    applied_ = wanted;
    return;
  }
  const double f_old = applied_.elastic_force_N(x);
  const double v_old = applied_.stored_energy_J(x);
  double offset = 0.0;
  const double x_force = wanted.depth_for_force_m(f_old);
  if (finite(x_force)) {
    offset = std::max(offset, indentation_m - x_force);
  }
  const double x_energy = wanted.depth_for_energy_m(v_old + tank_J_);
  if (finite(x_energy)) {
    offset = std::max(offset, indentation_m - x_energy);
  }
  if (offset > offset_m_) {
    ++offset_raises_;
  }
  const double f_new = wanted.elastic_force_N(indentation_m - offset);
  if (f_new < f_old * (1.0 - 1e-9) - 1e-12) {
    ++force_drops_;
  }
  const double v_new = wanted.stored_energy_J(indentation_m - offset);
  tank_J_ = std::clamp(tank_J_ + v_old - v_new, 0.0, tank_max_J_);  // >= 0 up to rounding; excess dissipated
  offset_m_ = offset;
  applied_ = wanted;
}

double PassiveTissueUpdate::force_N(double indentation_m, double rate_m_per_s) const noexcept {
  return applied_.force_N(indentation_m - offset_m_, rate_m_per_s);
}

model::CellImpedanceTarget PassiveTissueUpdate::target(double indentation_m, double force_ceiling_N,
                                                       double valid_until_s) const noexcept {
  return applied_.to_impedance_target(indentation_m - offset_m_, offset_m_, force_ceiling_N, valid_until_s);
}

// ---- passivity observer --------------------------------------------------------------------------

void PassivityObserver::observe(double force_N, double indentation_m) noexcept {
  if (!finite(force_N) || !finite(indentation_m)) {
    ++stats_.rejected_samples;
    return;
  }
  ++stats_.samples;
  if (primed_) {
    stats_.energy_J += 0.5 * (force_N + last_force_N_) * (indentation_m - last_indentation_m_);
    stats_.min_energy_J = std::min(stats_.min_energy_J, stats_.energy_J);
    if (stats_.energy_J < -tolerance_J_) {
      ++stats_.active_samples;
    }
  }
  primed_ = true;
  last_force_N_ = force_N;
  last_indentation_m_ = indentation_m;
}

double PassivityObserver::controller_damping_N_s_per_m(double rate_m_per_s, double dt_s,
                                                       double max_N_s_per_m) noexcept {
  const double deficit_J = -stats_.energy_J;
  if (!(deficit_J > tolerance_J_) || !(std::fabs(rate_m_per_s) > 1e-6) || !(dt_s > 0.0)) {
    return 0.0;
  }
  const double d = std::min(deficit_J / (rate_m_per_s * rate_m_per_s * dt_s), max_N_s_per_m);
  stats_.max_controller_damping_N_s_per_m = std::max(stats_.max_controller_damping_N_s_per_m, d);
  return d;
}

void accumulate(PassivityStats& total, const PassivityStats& cell) noexcept {
  total.energy_J += cell.energy_J;
  total.min_energy_J = std::min(total.min_energy_J, cell.min_energy_J);
  total.samples += cell.samples;
  total.active_samples += cell.active_samples;
  total.rejected_samples += cell.rejected_samples;
  total.max_controller_damping_N_s_per_m =
      std::max(total.max_controller_damping_N_s_per_m, cell.max_controller_damping_N_s_per_m);
}

void PassivityObserver::reset() noexcept {
  stats_ = {};
  primed_ = false;
  last_force_N_ = 0.0;
  last_indentation_m_ = 0.0;
}

}  // namespace mrskin::bridge
