// DeviceSession's valve currents: quantised once, sent in blocks of protocol::kMaxValveCurrents
// (all of them, or only those whose counts changed plus a rolling refresh). The real-time path:
// no allocation, no exception, no blocking.
#include <algorithm>
#include <cstring>

#include "mrskin/driver/session.hpp"
#include "mrskin/protocol/units.hpp"
#include "session_impl.hpp"

namespace mrskin {

namespace proto = mrskin::protocol;

ResultCode DeviceSession::Impl::quantise_changed_blocks(std::span<const double> current_A) noexcept {
  if (current_A.size() != current_counts_.size()) {
    ++counters_.invalid_commands;
    return ResultCode::invalid_value;
  }
  if (!connected_) {
    return ResultCode::disconnected;
  }
  // A block equal bitwise to the last command's (a hold, a resend) has its counts, already checked.
  // Ends with block_go_[b] = 2 for each block whose counts changed (those last sent: every
  // successful send leaves the unit's counts equal to current_counts_), else 0.
  proto::Identity scale;
  scale.current_lsb_nA = current_lsb_nA_;
  scale.current_max_counts = current_max_counts_;
  const std::size_t n = current_A.size();
  for (std::size_t b = 0; b < block_go_.size(); ++b) {
    const std::size_t first = b * proto::kMaxValveCurrents;
    const std::size_t end = std::min(n, first + proto::kMaxValveCurrents);
    const bool same = quantised_valid_ && std::memcmp(&current_A[first], &quantised_A_[first],
                                                      (end - first) * sizeof(double)) == 0;
    block_go_[b] = same ? 0 : 1;
    for (std::size_t v = first; v < end && !same; ++v) {
      const proto::Quantized<std::uint16_t> q = proto::quantize_current(current_A[v], scale);
      if (q.error != proto::Error::ok) {
        ++counters_.invalid_commands;
        return ResultCode::invalid_value;
      }
      pending_counts_[v] = q.counts;
    }
  }
  for (std::size_t b = 0; b < block_go_.size(); ++b) {
    if (block_go_[b] == 0) {
      continue;
    }
    const std::size_t first = b * proto::kMaxValveCurrents;
    const std::size_t end = std::min(n, first + proto::kMaxValveCurrents);
    unsigned changed = 0;
    for (std::size_t v = first; v < end; ++v) {
      changed |= pending_counts_[v] ^ current_counts_[v];
      current_counts_[v] = pending_counts_[v];
      commanded_A_[v] = static_cast<double>(current_counts_[v]) * info_.current_lsb_A;
    }
    std::memcpy(&quantised_A_[first], &current_A[first], (end - first) * sizeof(double));
    block_go_[b] = changed != 0 ? 2 : 0;
    counts_changed_since_reseed_ = counts_changed_since_reseed_ || changed != 0;
  }
  quantised_valid_ = true;
  currents_commanded_ = true;
  return ResultCode::ok;
}

ResultCode DeviceSession::Impl::send_blocks(TimePoint now) noexcept {
  const std::size_t n = current_counts_.size();
  for (std::size_t b = 0; b < block_go_.size(); ++b) {
    if (block_go_[b] != 2) {
      continue;
    }
    proto::ValveCurrents m;
    m.first = static_cast<std::uint16_t>(b * proto::kMaxValveCurrents);
    m.count = static_cast<std::uint8_t>(std::min(proto::kMaxValveCurrents, n - m.first));
    std::copy_n(current_counts_.begin() + m.first, m.count, m.counts.begin());
    const ResultCode rc = send_packet(m, /*hold=*/true);
    if (rc != ResultCode::ok) {
      drop_report();
      all_blocks_due_ = true;  // what reached the unit is unknown
      return rc;
    }
    block_sent_[b] = now;
  }
  const ResultCode rc = flush_report();
  if (rc != ResultCode::ok) {
    all_blocks_due_ = true;
    return rc;
  }
  all_blocks_due_ = false;
  oldest_block_sent_ = block_sent_.empty() ? now : *std::min_element(block_sent_.begin(), block_sent_.end());
  return ResultCode::ok;
}

// Blocks unsent for refresh_period, in turn from the cursor, so that a refresh of every valve
// spreads over the calls (a block that goes as changed is refreshed by it).
void DeviceSession::Impl::select_refresh(TimePoint now, Duration refresh_period,
                                         std::size_t max_refresh) noexcept {
  if (now - oldest_block_sent_ < refresh_period) {
    return;  // no block is due (most calls)
  }
  const std::size_t blocks = block_go_.size();
  for (std::size_t i = 0; i < blocks && max_refresh > 0; ++i) {
    const std::size_t b = refresh_cursor_ + i < blocks ? refresh_cursor_ + i : refresh_cursor_ + i - blocks;
    if (block_go_[b] == 0 && now - block_sent_[b] >= refresh_period) {
      block_go_[b] = 2;
      --max_refresh;
      refresh_cursor_ = b + 1 < blocks ? b + 1 : 0;
    }
  }
}

ResultCode DeviceSession::Impl::send_valve_currents(std::span<const double> current_A) noexcept {
  const ResultCode q = quantise_changed_blocks(current_A);
  if (q != ResultCode::ok) {
    return q;
  }
  std::fill(block_go_.begin(), block_go_.end(), std::uint8_t{2});
  return send_blocks(clock_.now());
}

ResultCode DeviceSession::Impl::send_valve_current_changes(std::span<const double> current_A, TimePoint now,
                                                           Duration refresh_period,
                                                           std::size_t max_refresh) noexcept {
  const ResultCode q = quantise_changed_blocks(current_A);
  if (q != ResultCode::ok) {
    return q;
  }
  if (all_blocks_due_) {
    std::fill(block_go_.begin(), block_go_.end(), std::uint8_t{2});
  }
  select_refresh(now, refresh_period, max_refresh);
  return send_blocks(now);
}

ResultCode DeviceSession::Impl::refresh_valve_currents(TimePoint now, Duration refresh_period,
                                                       std::size_t max_refresh) noexcept {
  if (!connected_) {
    return ResultCode::disconnected;
  }
  if (!currents_commanded_) {
    return ResultCode::ok;  // nothing to refresh
  }
  std::fill(block_go_.begin(), block_go_.end(), all_blocks_due_ ? std::uint8_t{2} : std::uint8_t{0});
  select_refresh(now, refresh_period, max_refresh);
  return send_blocks(now);
}

ResultCode DeviceSession::send_valve_currents(std::span<const double> current_A) noexcept {
  return impl_->send_valve_currents(current_A);
}
ResultCode DeviceSession::send_valve_current_changes(std::span<const double> current_A, TimePoint now,
                                                     Duration refresh_period,
                                                     std::size_t max_refresh) noexcept {
  return impl_->send_valve_current_changes(current_A, now, refresh_period, max_refresh);
}
TimePoint DeviceSession::valve_refresh_due(Duration refresh_period) const noexcept {
  return impl_->valve_refresh_due(refresh_period);
}
ResultCode DeviceSession::refresh_valve_currents(TimePoint now, Duration refresh_period,
                                                 std::size_t max_refresh) noexcept {
  return impl_->refresh_valve_currents(now, refresh_period, max_refresh);
}
std::size_t DeviceSession::valve_current_blocks() const noexcept { return impl_->valve_current_blocks(); }

}  // namespace mrskin
