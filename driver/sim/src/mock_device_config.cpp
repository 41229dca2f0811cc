// The mock unit's configuration memory: reads (answered at once, or with the next telemetry
// report on a bus whose slots the samples take) and versioned calibration writes.
#include <algorithm>
#include <cstdint>
#include <span>
#include <string_view>
#include <vector>

#include "mock_device_impl.hpp"
#include "mrskin/protocol/packed_report.hpp"

namespace mrskin::sim {
namespace proto = mrskin::protocol;

namespace {

// The N of the first "version = N" line of a calibration, or -1.
long calibration_version(std::span<const std::uint8_t> blob) noexcept {
  constexpr std::string_view key = "version";
  std::size_t i = 0;
  while (i < blob.size()) {  // i is at a line start
    std::size_t k = 0;
    while (k < key.size() && i + k < blob.size() && blob[i + k] == static_cast<std::uint8_t>(key[k])) {
      ++k;
    }
    if (k == key.size()) {
      std::size_t j = i + k;
      while (j < blob.size() && (blob[j] == ' ' || blob[j] == '=')) {
        ++j;
      }
      long version = 0;
      bool digits = false;
      while (j < blob.size() && blob[j] >= '0' && blob[j] <= '9' && version < 100000000) {
        version = version * 10 + (blob[j] - '0');
        digits = true;
        ++j;
      }
      return digits ? version : -1;
    }
    while (i < blob.size() && blob[i] != '\n') {
      ++i;
    }
    ++i;
  }
  return -1;
}

}  // namespace

void MockDevice::Impl::handle_config(const proto::Message& message) noexcept {
  auto blob_for = [this](std::uint16_t key) -> std::vector<std::uint8_t>* {
    switch (static_cast<proto::ConfigKey>(key)) {
      case proto::ConfigKey::profile:
        return &profile_blob_;
      case proto::ConfigKey::calibration:
        return &calibration_blob_;
    }
    return nullptr;
  };
  if (const auto* r = std::get_if<proto::ConfigRead>(&message)) {
    const std::vector<std::uint8_t>* blob = blob_for(r->key);
    if (blob == nullptr || r->offset > blob->size()) {
      send_message(
          proto::ConfigAck{r->key, r->offset,
                           static_cast<std::uint8_t>(blob == nullptr ? proto::ConfigStatus::bad_key
                                                                     : proto::ConfigStatus::bad_range)});
      return;
    }
    if (config_replies_ride_telemetry() && r->length <= config_bytes_beside_telemetry_ &&
        pending_read_count_ < pending_reads_.size()) {
      pending_reads_[pending_read_count_++] = *r;
      return;
    }
    send_message(config_data_for(*r));  // at once, in a report of its own
  } else if (const auto* w = std::get_if<proto::ConfigWrite>(&message)) {
    // Only the calibration is writable, only while the coils are off, in order, and only
    // with a version above the stored one (checked when the last chunk arrives).
    auto status = proto::ConfigStatus::ok;
    std::vector<std::uint8_t>& pending = calibration_pending_;
    if (static_cast<proto::ConfigKey>(w->key) != proto::ConfigKey::calibration) {
      status = proto::ConfigStatus::rejected;
    } else if (state_.load() == static_cast<std::uint8_t>(proto::DeviceState::enabled)) {
      status = proto::ConfigStatus::busy;
    } else if (w->total > kConfigCapacity || w->total == 0 || w->offset + w->length > w->total) {
      status = proto::ConfigStatus::bad_range;
    } else {
      const bool repeat_of_committed =
          pending.empty() && w->total == calibration_blob_.size() && w->offset + w->length == w->total &&
          std::equal(w->bytes.begin(), w->bytes.begin() + w->length, calibration_blob_.begin() + w->offset);
      if (w->offset == 0) {
        pending.clear();  // a new write (or its first chunk again); within reserve: no allocation
      }
      if (repeat_of_committed) {
        // The last chunk again (its ack was lost): already stored.
      } else if (w->offset == pending.size()) {
        pending.insert(pending.end(), w->bytes.begin(), w->bytes.begin() + w->length);
      } else if (w->offset + w->length != pending.size()) {
        status = proto::ConfigStatus::bad_range;  // chunks must arrive in order (a repeat is fine)
      }
      if (status == proto::ConfigStatus::ok && !repeat_of_committed && pending.size() == w->total &&
          w->offset + w->length == w->total) {
        if (calibration_version(pending) > calibration_version(calibration_blob_)) {
          calibration_blob_.swap(pending);  // both reserved: no allocation
        } else {
          status = proto::ConfigStatus::rejected;
        }
        pending.clear();
      }
    }
    send_message(proto::ConfigAck{w->key, w->offset, static_cast<std::uint8_t>(status)});
  }
}

proto::ConfigData MockDevice::Impl::config_data_for(const proto::ConfigRead& r) const noexcept {
  const std::vector<std::uint8_t>& blob =
      static_cast<proto::ConfigKey>(r.key) == proto::ConfigKey::profile ? profile_blob_ : calibration_blob_;
  const std::size_t offset = std::min<std::size_t>(r.offset, blob.size());
  proto::ConfigData data;
  data.key = r.key;
  data.offset = r.offset;
  data.total = static_cast<std::uint16_t>(blob.size());
  data.length = static_cast<std::uint8_t>(std::min<std::size_t>(r.length, blob.size() - offset));
  std::copy_n(blob.begin() + static_cast<std::ptrdiff_t>(offset), data.length, data.bytes.begin());
  return data;
}

void MockDevice::Impl::append_pending_config_replies() noexcept {
  std::size_t done = 0;
  for (; done < pending_read_count_; ++done) {
    const proto::EncodeResult e =
        proto::append_packet(config_data_for(pending_reads_[done]), tx_sequence_,
                             std::span<std::uint8_t>(report_.bytes).first(report_capacity_), report_.length);
    if (e.error != proto::Error::ok) {
      break;  // no room left in this report: the next sample's carries it
    }
    ++tx_sequence_;
    report_.length = static_cast<std::uint16_t>(report_.length + e.bytes);
  }
  std::copy(pending_reads_.begin() + static_cast<std::ptrdiff_t>(done),
            pending_reads_.begin() + static_cast<std::ptrdiff_t>(pending_read_count_),
            pending_reads_.begin());
  pending_read_count_ -= done;
}

}  // namespace mrskin::sim
