// DeviceSession's traffic log: the ring of the last packets, its copy at the last fault, and
// their decoding into SI units and text. Off the tick thread (allocates).
#include <fmt/format.h>

#include <algorithm>
#include <string>
#include <vector>

#include "mrskin/driver/session.hpp"
#include "mrskin/protocol/packet.hpp"
#include "mrskin/protocol/units.hpp"
#include "session_impl.hpp"
#include "session_names.hpp"

namespace mrskin {
namespace proto = mrskin::protocol;
using session_names::config_key_name;
using session_names::config_status_name;
using session_names::quantity_unit;
using session_names::request_name;

std::vector<TrafficRecord> DeviceSession::Impl::ring_log() const {
  std::vector<TrafficRecord> out;
  out.reserve(ring_size_);
  const std::size_t start = (ring_next_ + ring_.size() - ring_size_) % ring_.size();
  for (std::size_t i = 0; i < ring_size_; ++i) {
    out.push_back(ring_[(start + i) % ring_.size()]);
  }
  return out;
}

std::vector<TrafficRecord> DeviceSession::Impl::fault_log() const {
  std::vector<TrafficRecord> out;
  out.reserve(fault_ring_size_);
  const std::size_t start = (fault_ring_next_ + fault_ring_.size() - fault_ring_size_) % fault_ring_.size();
  for (std::size_t i = 0; i < fault_ring_size_; ++i) {
    out.push_back(fault_ring_[(start + i) % fault_ring_.size()]);
  }
  return out;
}

std::vector<LogEntry> DeviceSession::Impl::decode_log(const std::vector<TrafficRecord>& records) const {
  std::vector<LogEntry> out;
  out.reserve(records.size());
  for (const TrafficRecord& r : records) {
    LogEntry e;
    e.host_time = r.time;
    e.sent = r.sent;
    const proto::PacketDecoded p =
        proto::decode_packet(std::span<const std::uint8_t>(r.packet.bytes.data(), r.packet.length));
    if (p.error != proto::Error::ok) {
      e.kind = "undecodable";
      e.error = proto::to_string(p.error);
      std::string hex;
      for (std::size_t i = 0; i < r.packet.length; ++i) {
        hex += fmt::format("{}{:02x}", i == 0 ? "" : " ", r.packet.bytes[i]);
      }
      e.detail = hex;
      out.push_back(std::move(e));
      continue;
    }
    e.sequence = p.sequence;
    if (const auto* v = std::get_if<proto::ValveCurrents>(&p.message)) {
      e.kind = "currents";
      e.first = v->first;
      e.unit = "A";
      for (std::size_t i = 0; i < v->count; ++i) {
        e.values.push_back(static_cast<double>(v->counts[i]) * info_.current_lsb_A);
      }
    } else if (const auto* t = std::get_if<proto::CellTargets>(&p.message)) {
      e.kind = "targets";
      e.first = t->first;
      for (std::size_t i = 0; i < t->count; ++i) {
        e.targets.push_back(proto::cell_target_to_si(t->targets[i]));
      }
    } else if (const auto* m = std::get_if<proto::Telemetry>(&p.message)) {
      e.kind = "telemetry";
      e.has_device_time = true;
      e.device_time_us = m->device_time_us;
      e.first = m->first;
      e.unit = quantity_unit(identity_.sensor_quantity);
      for (std::size_t i = 0; i < m->count; ++i) {
        e.values.push_back(static_cast<double>(m->counts[i]) * info_.sensor_lsb);
      }
    } else if (const auto* ts = std::get_if<proto::TimeSync>(&p.message)) {
      e.kind = "time sync";
      e.has_device_time = true;
      e.device_time_us = ts->device_time_us;
    } else if (const auto* s = std::get_if<proto::Status>(&p.message)) {
      e.kind = "status";
      e.state = to_string(static_cast<DeviceState>(s->state));
      e.fault = fault_name(s->fault);
      std::string flags;
      for (const auto& [bit, name] :
           {std::pair{proto::kFlagValvesReleased, "valves released"},
            std::pair{proto::kFlagDerated, "derated"}, std::pair{proto::kFlagCalibrated, "calibrated"},
            std::pair{proto::kFlagDegaussing, "degaussing"}}) {
        if ((s->flags & bit) != 0) {
          flags += flags.empty() ? name : fmt::format(", {}", name);
        }
      }
      e.detail = flags.empty() ? std::string("no flags") : flags;
      if (s->fault_detail != 0) {
        e.detail += fmt::format("; detail {}", s->fault_detail);
      }
    } else if (const auto* h = std::get_if<proto::Heartbeat>(&p.message)) {
      e.kind = "heartbeat";
      e.detail = fmt::format("counter {}", h->counter);
    } else if (const auto* q = std::get_if<proto::StateRequest>(&p.message)) {
      e.kind = "state request";
      e.state = request_name(q->request);
    } else if (const auto* ir = std::get_if<proto::IdentifyRequest>(&p.message)) {
      e.kind = "identify";
      e.detail = fmt::format("host speaks v{}.{}", ir->host_major, ir->host_minor);
    } else if (const auto* id = std::get_if<proto::Identity>(&p.message)) {
      e.kind = "identity";
      e.detail =
          fmt::format("v{}.{}, firmware {}.{}.{}, serial {:08X}, {} x {}", id->proto_major, id->proto_minor,
                      id->fw_major, id->fw_minor, id->fw_patch, id->serial, id->rows, id->cols);
    } else if (const auto* cr = std::get_if<proto::ConfigRead>(&p.message)) {
      e.kind = "config read";
      e.detail =
          fmt::format("{} bytes {}..{}", config_key_name(cr->key), cr->offset, cr->offset + cr->length);
    } else if (const auto* cd = std::get_if<proto::ConfigData>(&p.message)) {
      e.kind = "config data";
      e.detail = fmt::format("{} bytes {}..{} of {}", config_key_name(cd->key), cd->offset,
                             cd->offset + cd->length, cd->total);
    } else if (const auto* cw = std::get_if<proto::ConfigWrite>(&p.message)) {
      e.kind = "config write";
      e.detail = fmt::format("{} bytes {}..{} of {}", config_key_name(cw->key), cw->offset,
                             cw->offset + cw->length, cw->total);
    } else if (const auto* ca = std::get_if<proto::ConfigAck>(&p.message)) {
      e.kind = "config ack";
      e.detail =
          fmt::format("{} at {}: {}", config_key_name(ca->key), ca->offset, config_status_name(ca->status));
    } else if (const auto* us = std::get_if<proto::UsbSlots>(&p.message)) {
      e.kind = "usb slots";
      e.detail = fmt::format("{} reports of {} bytes every {} us", us->reports_per_interval, us->report_bytes,
                             us->interval_us);
    } else if (const auto* sd = std::get_if<proto::SensorDeadband>(&p.message)) {
      e.kind = "sensor deadband";
      e.detail = fmt::format("{} counts", sd->counts);
    }
    out.push_back(std::move(e));
  }
  return out;
}

std::string DeviceSession::Impl::format_log(const std::vector<TrafficRecord>& records) const {
  std::string out;
  for (const LogEntry& e : decode_log(records)) {
    out += fmt::format("{:12.6f} s {} ", to_seconds(e.host_time), e.sent ? "tx" : "rx");
    if (e.sequence >= 0) {
      out += fmt::format("#{:<3} ", e.sequence);
    } else {
      out += "#?   ";
    }
    out += fmt::format("{:<13}", e.kind);
    if (e.has_device_time) {
      out += fmt::format(" device {:.6f} s", static_cast<double>(e.device_time_us) * 1e-6);
    }
    if (!e.error.empty()) {
      out += fmt::format(" {}:", e.error);
    }
    if (e.kind == "currents" || e.kind == "telemetry") {
      out += fmt::format(" {} {}..{} [{}]:", e.kind == "currents" ? "valves" : "sensors", e.first,
                         e.first + e.values.size() - 1, e.unit);
      for (const double v : e.values) {
        out += e.kind == "currents" ? fmt::format(" {:.6f}", v) : fmt::format(" {:.4g}", v);
      }
    }
    std::size_t cell = e.first;
    for (const proto::CellTargetSi& t : e.targets) {
      out += fmt::format(" cell {}: {:g} N/m from {:.3f} mm, ceiling {:.3f} N, valid {:.2f} s;", cell++,
                         t.stiffness_N_per_m, t.offset_m * 1e3, t.ceiling_N, t.validity_s);
    }
    if (!e.state.empty()) {
      out += fmt::format(" {}", e.state);
    }
    if (!e.fault.empty()) {
      out += fmt::format(" (fault: {})", e.fault);
    }
    if (!e.detail.empty()) {
      out += fmt::format(" {}", e.detail);
    }
    out += '\n';
  }
  return out;
}

std::string DeviceSession::Impl::fault_report() const {
  if (counters_.faults == 0) {
    return {};
  }
  std::string out = fmt::format(
      "fault: {} at {:.6f} s (host time); {} fault(s) so far; state now {}{}\n"
      "last {} packets before it, oldest first:\n",
      fault_name(last_fault_code_), to_seconds(last_fault_time_), counters_.faults, to_string(state_),
      state_ == DeviceState::fault ? fmt::format(" ({})", fault_name(fault_)) : std::string(),
      fault_ring_size_);
  out += format_log(fault_log());
  return out;
}

}  // namespace mrskin
