// Log-spaced histogram of durations from 10 ns to 10 s, 16 buckets per decade: fixed
// size, no allocation, so the tick can fill it.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>

namespace mrskin {

class DurationHistogram {
 public:
  void add(std::int64_t ns) noexcept {
    ++count_;
    max_ns_ = std::max(max_ns_, ns);
    std::size_t index = 0;
    if (ns >= 10) {
      const double pos = (std::log10(static_cast<double>(ns)) - 1.0) * kPerDecade;
      index = static_cast<std::size_t>(std::min(pos + 1.0, static_cast<double>(buckets_.size() - 1)));
    }
    ++buckets_[index];
  }
  // Upper edge of the bucket holding quantile q (never above the largest value); 0 if empty.
  [[nodiscard]] double percentile_ns(double q) const noexcept {
    if (count_ == 0) {
      return 0.0;
    }
    const auto rank = static_cast<std::uint64_t>(std::ceil(q * static_cast<double>(count_)));
    std::uint64_t seen = 0;
    for (std::size_t i = 0; i < buckets_.size(); ++i) {
      seen += buckets_[i];
      if (seen >= rank && buckets_[i] > 0) {
        if (i == 0) {
          return 10.0;
        }
        const double upper = std::pow(10.0, 1.0 + static_cast<double>(i) / kPerDecade);
        return std::min(upper, static_cast<double>(max_ns_));
      }
    }
    return static_cast<double>(max_ns_);
  }
  [[nodiscard]] std::uint64_t count() const noexcept { return count_; }
  [[nodiscard]] std::int64_t max_ns() const noexcept { return max_ns_; }
  // The buckets, for printing a histogram: bucket i counts durations up to upper_edge_ns(i)
  // (bucket 0: below 10 ns; the last also holds everything above 10 s).
  [[nodiscard]] static constexpr std::size_t bucket_count() noexcept { return kBuckets; }
  [[nodiscard]] std::uint64_t bucket(std::size_t i) const noexcept { return i < kBuckets ? buckets_[i] : 0; }
  [[nodiscard]] static double upper_edge_ns(std::size_t i) noexcept {
    return i == 0 ? 10.0 : std::pow(10.0, 1.0 + static_cast<double>(i) / kPerDecade);
  }
  void reset() noexcept { *this = DurationHistogram{}; }

 private:
  static constexpr int kPerDecade = 16;
  static constexpr int kDecades = 9;
  static constexpr std::size_t kBuckets = (static_cast<std::size_t>(kPerDecade) * kDecades) + 2;
  std::array<std::uint64_t, kBuckets> buckets_{};
  std::uint64_t count_ = 0;
  std::int64_t max_ns_ = 0;
};

}  // namespace mrskin
