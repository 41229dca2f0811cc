#include "mock_bus.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <span>
#include <variant>

#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/packed_report.hpp"
#include "mrskin/protocol/usb.hpp"

namespace mrskin::sim {
namespace proto = mrskin::protocol;

namespace {

constexpr std::int64_t kNever = std::numeric_limits<std::int64_t>::max();

std::int64_t floor_div(std::int64_t a, std::int64_t b) noexcept {
  const std::int64_t q = a / b;
  return (a % b != 0 && (a < 0) != (b < 0)) ? q - 1 : q;
}

void raise(std::atomic<std::int64_t>& value, std::int64_t candidate) noexcept {
  std::int64_t seen = value.load(std::memory_order_relaxed);
  while (candidate > seen && !value.compare_exchange_weak(seen, candidate, std::memory_order_relaxed)) {
  }
}

// Whether every packet of the report is telemetry: a newer sample may take its place. A packed
// report (protocol 1.2) that also carries a status or an echo keeps its place.
bool is_telemetry(const Datagram& d) noexcept {
  proto::PacketWalker walker(std::span<const std::uint8_t>(d.bytes.data(), d.length));
  proto::PacketDecoded p;
  bool any = false;
  while (walker.next(p)) {
    if (p.error != proto::Error::ok || !std::holds_alternative<proto::Telemetry>(p.message)) {
      return false;
    }
    any = true;
  }
  return any;
}

// A report that carries telemetry only: its first packet's first sensor, the block a newer
// sample of the same sensors replaces while it waits (a 16 x 16 unit sends six blocks a
// sample); -1 for any other report.
std::int32_t telemetry_block_of(const Datagram& d) noexcept {
  if (!is_telemetry(d)) {
    return -1;
  }
  proto::PacketWalker walker(std::span<const std::uint8_t>(d.bytes.data(), d.length));
  proto::PacketDecoded p;
  const proto::Telemetry* t = walker.next(p) ? std::get_if<proto::Telemetry>(&p.message) : nullptr;
  return t == nullptr ? -1 : t->first;
}

// Packets a report carries: one in protocol 1.1, one or more in a packed report (1.2). Each
// packet the walk steps over counts, whether or not its content decodes; a report with none
// (empty, or 0x00 first) counts as one, as v1 counted it.
std::uint64_t packets_in(const Datagram& d) noexcept {
  proto::PacketWalker walker(std::span<const std::uint8_t>(d.bytes.data(), d.length));
  std::uint64_t n = 0;
  while (walker.skip()) {  // the framing only: a count needs no payload decoded
    ++n;
  }
  return std::max<std::uint64_t>(n, 1);
}

}  // namespace

const char* to_string(MockBusKind kind) noexcept {
  switch (kind) {
    case MockBusKind::none:
      return "none";
    case MockBusKind::hid_fs:
      return "hid-fs";
    case MockBusKind::hid_hs:
      return "hid-hs";
    case MockBusKind::can:
      return "can";
    case MockBusKind::canfd:
      return "canfd";
  }
  return "none";
}

void MockBus::Counters::waited(std::int64_t ns) noexcept { raise(max_wait_ns, ns); }

void MockBus::Counters::carry(const Datagram& report) noexcept {
  packets.bump(packets_in(report));
  carried.bump();
  bytes.bump(report.length);
}

MockBus::MockBus(const MockBusOptions& options)
    : options_(options),
      to_device_waiting_(usb() ? options.usb_queue_reports + proto::kUsbHighSpeedMaxReportsPerMicroframe + 1
                               : 0),
      to_host_waiting_(usb() ? options.usb_queue_reports + proto::kUsbHighSpeedMaxReportsPerMicroframe + 1
                             : 0),
      host_codec_(CanRole::host, options.can_node, options.kind == MockBusKind::canfd),
      device_codec_(CanRole::device, options.can_node, options.kind == MockBusKind::canfd),
      trial_codec_(device_codec_),
      host_(can() ? options.can_send_queue_packets : 0, can() ? options.can_txqueuelen_frames : 0),
      device_(can() ? options.can_send_queue_packets : 0, can() ? options.can_txqueuelen_frames : 0) {
  const proto::UsbInterruptSlots slots = declared_usb_slots(options).value_or(proto::kUsbFullSpeedSlots);
  interval_ns_ = std::llround(slots.interval_s * 1e9);
  reports_per_interval_ = slots.reports_per_interval;
  report_bytes_per_s_ = proto::usb_report_bytes_per_s(slots);
  const CanTransportOptions transport{};
  backoff_min_ns_ = transport.enobufs_backoff_min.count();
  backoff_max_ns_ = transport.enobufs_backoff_max.count();
}

bool MockBus::usb() const noexcept {
  return options_.kind == MockBusKind::hid_fs || options_.kind == MockBusKind::hid_hs;
}
bool MockBus::can() const noexcept {
  return options_.kind == MockBusKind::can || options_.kind == MockBusKind::canfd;
}

void MockBus::start(TimePoint t) noexcept {
  if (started_) {
    return;
  }
  started_ = true;
  clock_ns_ = bus_free_ns_ = t.count();
  start_ns_.store(t.count(), std::memory_order_relaxed);
  last_ns_.store(t.count(), std::memory_order_relaxed);
  // No report of the past: the first slot is the frame the unit starts in.
  const auto first = static_cast<std::int64_t>(reports_per_interval_) * floor_div(t.count(), interval_ns_);
  to_device_lane_.next_slot = to_host_lane_.next_slot = first;
}

void MockBus::note_time(std::int64_t t_ns) noexcept { raise(last_ns_, t_ns); }

bool MockBus::usb_schedule(UsbLane& lane, TimePoint t, TimePoint& due) const noexcept {
  const auto per = static_cast<std::int64_t>(reports_per_interval_);
  const std::int64_t frame = floor_div(t.count(), interval_ns_);
  const std::int64_t first = frame * per;
  const std::int64_t slot = std::max(lane.next_slot, first);
  // Reports already waiting for a later frame than this one, ahead of this report.
  const std::int64_t ahead = slot - (first + per);
  if (ahead >= static_cast<std::int64_t>(options_.usb_queue_reports)) {
    return false;
  }
  lane.next_slot = slot + 1;
  const std::int64_t slot_frame = floor_div(slot, per);
  due = slot_frame == frame ? t : TimePoint{slot_frame * interval_ns_};
  return true;
}

MockBus::UsbPlace MockBus::usb_place(UsbLane& lane, BusRing<Waiting>& waiting, Counters& counters,
                                     const Datagram& d, TimePoint t) const noexcept {
  TimePoint due{};
  if (waiting.full() || !usb_schedule(lane, t, due)) {
    counters.dropped.bump();
    return UsbPlace::dropped;
  }
  counters.waited((due - t).count());
  if (due == t && waiting.empty()) {
    counters.carry(d);
    return UsbPlace::now;
  }
  waiting.push() = Waiting{due, t, d};
  return UsbPlace::later;
}

void MockBus::note_handshake(const Datagram& d, CanRole sender) noexcept {
  // Both codecs learn both versions (1.2's delta blocks), the handshake before the bus starts too.
  if (can()) {
    const std::span<const std::uint8_t> bytes(d.bytes.data(), d.length);
    host_codec_.note_handshake(bytes, sender);
    device_codec_.note_handshake(bytes, sender);
  }
}

void MockBus::host_sent(const Datagram& d, TimePoint t, BusSink& sink) noexcept {
  note_handshake(d, CanRole::host);
  if (!started_) {
    sink.deliver_to_device(d, t);  // before the unit's first step: an ideal link, not counted
    return;
  }
  note_time(t.count());
  if (usb()) {
    // The host's packets come in the order it sent them: none before one already handed over.
    t = std::max(t, host_last_);
    host_last_ = t;
    if (usb_place(to_device_lane_, to_device_waiting_, to_device_, d, t) == UsbPlace::now) {
      sink.deliver_to_device(d, t);
    }
    return;
  }
  if (can()) {
    if (host_.packets.full()) {
      to_device_.dropped.bump();  // the transport's send() would refuse it (would_block)
      return;
    }
    if (!encode(host_codec_, d, scratch_)) {
      to_device_.unsent.bump();
      return;
    }
    CanPacket& p = host_.packets.push();
    p = scratch_;
    p.submit_ns = std::max(t.count(), clock_ns_);
    to_device_.unsent.bump(p.unsent);
    return;
  }
  to_device_.carry(d);
  sink.deliver_to_device(d, t);
}

void MockBus::host_sent_while_lagging(const Datagram& d, TimePoint t, BusSink& sink) noexcept {
  const bool host_waiting = usb() ? !to_device_waiting_.empty() : (can() && !host_.packets.empty());
  if (!started_ || host_waiting || !(usb() || can())) {  // an ideal link has nothing to bypass
    host_sent(d, t, sink);
    return;
  }
  note_handshake(d, CanRole::host);
  if (usb()) {
    host_last_ = std::max(t, host_last_);
  }
  host_while_lagging_.bump();
  sink.deliver_to_device(d, t);
}

bool MockBus::device_slot_free(TimePoint t) const noexcept {
  if (!started_ || !usb()) {
    return true;
  }
  UsbLane lane = to_host_lane_;  // a trial: nothing is booked
  TimePoint due{};
  return usb_schedule(lane, t, due) && due == t;
}

void MockBus::device_sent(const Datagram& d, TimePoint t, BusSink& sink) noexcept {
  note_handshake(d, CanRole::device);
  if (!started_) {
    sink.deliver_to_host(d, t);
    return;
  }
  note_time(t.count());
  if (usb()) {
    usb_device_sent(d, t, sink);
  } else if (can()) {
    can_device_sent(d, t);
  } else {
    to_host_.carry(d);
    sink.deliver_to_host(d, t);
  }
}

void MockBus::usb_device_sent(const Datagram& d, TimePoint t, BusSink& sink) noexcept {
  const std::int32_t block = telemetry_block_of(d);
  if (block >= 0) {
    for (std::size_t i = to_host_waiting_.size(); i > 0; --i) {
      Waiting& w = to_host_waiting_.at(i - 1);
      if (w.telemetry_block < 0) {
        break;  // taking a place ahead of a status or an answer would reorder the packets
      }
      if (w.telemetry_block == block) {
        // The same sensors' sample still waits for its slot: this newer one takes its place.
        w.datagram = d;
        w.submitted = t;
        to_host_.dropped.bump();
        return;
      }
    }
  }
  switch (usb_place(to_host_lane_, to_host_waiting_, to_host_, d, t)) {
    case UsbPlace::now:
      sink.deliver_to_host(d, t);
      break;
    case UsbPlace::later:
      to_host_waiting_.at(to_host_waiting_.size() - 1).telemetry_block = block;
      break;
    case UsbPlace::dropped:
      break;
  }
}

void MockBus::can_device_sent(const Datagram& d, TimePoint t) noexcept {
  CanNode& node = device_;
  if (const std::int32_t block = telemetry_block_of(d); block >= 0) {
    // A sample of the same sensors none of whose frames is written yet gives its place to this
    // newer one.
    for (std::size_t i = node.packets.size(); i > node.written; --i) {
      CanPacket& waiting = node.packets.at(i - 1);
      if (!(i - 1 == node.written && node.next_frame > 0) && telemetry_block_of(waiting.datagram) == block) {
        // A trial on a copy: the codec's counters and delta blocks move only if the sample goes.
        // With delta blocks the replaced sample's blocks count as sent: a block that changed in it
        // alone reaches the host's codec at its refresh (the bus delivers the packet whole).
        trial_codec_ = device_codec_;
        if (!encode(trial_codec_, d, scratch_) || scratch_.frame_count != waiting.frame_count) {
          break;
        }
        device_codec_ = trial_codec_;
        const std::int64_t submitted = waiting.submit_ns;
        waiting = scratch_;
        waiting.submit_ns = submitted;
        to_host_.dropped.bump();
        return;
      }
    }
  }
  if (!encode(device_codec_, d, scratch_)) {
    to_host_.unsent.bump();
    return;
  }
  if (node.packets.full()) {
    to_host_.dropped.bump();
    return;
  }
  CanPacket& p = node.packets.push();
  p = scratch_;
  p.submit_ns = std::max(t.count(), clock_ns_);
  to_host_.unsent.bump(p.unsent);
}

bool MockBus::encode(CanPacketCodec& codec, const Datagram& d, CanPacket& out) noexcept {
  out.datagram = d;
  out.frame_count = 0;
  out.unsent = 0;
  const std::span<const std::uint8_t> bytes(d.bytes.data(), d.length);
  if (codec.fd() || packets_in(d) == 1) {
    // One packet, or a packed report in one CAN FD frame: delivered whole with its last frame.
    if (!encode_packet_frames(codec, d, 0, d.length, out)) {
      return false;
    }
  } else {
    // A packed report on classic CAN: each packet's frames, as the CAN transport writes them.
    proto::PacketWalker walker(bytes);
    proto::PacketDecoded p;
    std::size_t begin = 0;
    while (walker.next(p)) {
      if (p.error != proto::Error::ok || !encode_packet_frames(codec, d, begin, walker.offset(), out)) {
        return false;
      }
      begin = walker.offset();
    }
  }
  // No frame: packets this framing has no form for (classic CAN's heartbeat echo); the CAN
  // transport drops them too.
  return out.frame_count > 0;
}

bool MockBus::encode_packet_frames(CanPacketCodec& codec, const Datagram& d, std::size_t begin,
                                   std::size_t end, CanPacket& out) noexcept {
  const CanPacketCodec::Encoded e =
      codec.encode(std::span<const std::uint8_t>(d.bytes.data() + begin, end - begin), frames_);
  if (e.error != proto::Error::ok || out.frame_count + e.frames > out.frames.size()) {
    return false;
  }
  out.unsent += e.unsent;
  for (std::size_t i = 0; i < e.frames; ++i) {
    out.frames[out.frame_count++] = {frames_[i].id, frames_[i].length, frames_[i].fd, 0, 0};
  }
  if (e.frames > 0) {
    FrameInfo& last = out.frames[out.frame_count - 1];
    last.packet_begin = static_cast<std::uint8_t>(begin);
    last.packet_end = static_cast<std::uint8_t>(end);
  }
  return true;
}

std::int64_t MockBus::frame_ns(const FrameInfo& f) const noexcept {
  return std::llround(proto::can_frame_time_worst_case_s(f.data_bytes, f.fd,
                                                         options_.nominal_bitrate_bit_per_s,
                                                         options_.data_bitrate_bit_per_s) *
                      1e9);
}

void MockBus::can_write(CanNode& node, bool host, std::int64_t t_ns) noexcept {
  while (node.has_unwritten()) {
    const CanPacket& p = node.packets.at(node.written);
    while (node.next_frame < p.frame_count) {
      if (node.tx.full()) {
        if (host) {
          // The transport's I/O thread: the interface's queue answers ENOBUFS; the frame is
          // written again after a backoff that doubles while it lasts (CanTransportOptions).
          enobufs_.bump();
          node.backoff_ns = std::clamp<std::int64_t>(node.backoff_ns * 2, backoff_min_ns_, backoff_max_ns_);
          node.retry_ns = t_ns + node.backoff_ns;
        }
        return;
      }
      QueuedFrame& f = node.tx.push();
      f.frame = p.frames[node.next_frame];
      f.submit_ns = t_ns;
      f.last = ++node.next_frame == p.frame_count;
      node.backoff_ns = 0;
    }
    ++node.written;
    node.next_frame = 0;
  }
}

void MockBus::can_start(std::int64_t t_ns) noexcept {
  // Arbitration: the lowest identifier among the frames waiting at the queues' heads.
  const bool host_ready = !host_.tx.empty() && host_.tx.front().submit_ns <= t_ns;
  const bool device_ready = !device_.tx.empty() && device_.tx.front().submit_ns <= t_ns;
  const bool host_wins =
      host_ready && (!device_ready || host_.tx.front().frame.id < device_.tx.front().frame.id);
  BusRing<QueuedFrame>& queue = host_wins ? host_.tx : device_.tx;
  on_bus_.frame = queue.front();
  on_bus_.from_host = host_wins;
  queue.pop();
  const std::int64_t duration = frame_ns(on_bus_.frame.frame);
  on_bus_.end_ns = t_ns + duration;
  busy_ = true;
  Counters& c = host_wins ? to_device_ : to_host_;
  c.carried.bump();
  c.bytes.bump(on_bus_.frame.frame.data_bytes);
  c.busy_ns.fetch_add(duration, std::memory_order_relaxed);
}

void MockBus::can_complete(BusSink& sink) noexcept {
  busy_ = false;
  bus_free_ns_ = on_bus_.end_ns;
  const FrameInfo& f = on_bus_.frame.frame;
  if (f.packet_end == 0) {
    return;
  }
  CanNode& node = on_bus_.from_host ? host_ : device_;
  Counters& c = on_bus_.from_host ? to_device_ : to_host_;
  const CanPacket& p = node.packets.front();
  Datagram d;  // the packet (or the FD frame's packed report) this frame completes
  d.length = static_cast<std::uint16_t>(f.packet_end - f.packet_begin);
  std::copy_n(p.datagram.bytes.begin() + f.packet_begin, d.length, d.bytes.begin());
  c.packets.bump(packets_in(d));
  c.waited(on_bus_.end_ns - p.submit_ns);
  if (on_bus_.frame.last) {
    node.packets.pop();
    --node.written;
  }
  if (on_bus_.from_host) {
    sink.deliver_to_device(d, TimePoint{on_bus_.end_ns});
  } else {
    sink.deliver_to_host(d, TimePoint{on_bus_.end_ns});
  }
}

void MockBus::advance(TimePoint t, BusSink& sink) noexcept {
  if (!started_) {
    return;
  }
  const std::int64_t until = t.count();
  note_time(until);
  if (usb()) {
    while (!to_host_waiting_.empty() && to_host_waiting_.front().due <= t) {
      const Waiting w = to_host_waiting_.front();
      to_host_waiting_.pop();
      to_host_.carry(w.datagram);
      sink.deliver_to_host(w.datagram, w.due);
    }
    while (!to_device_waiting_.empty() && to_device_waiting_.front().due <= t) {
      const Waiting w = to_device_waiting_.front();
      to_device_waiting_.pop();
      to_device_.carry(w.datagram);
      sink.deliver_to_device(w.datagram, w.due);
    }
    return;
  }
  if (!can()) {
    return;
  }
  // Events in time order: a frame finishing, the host writing frames, the unit feeding its
  // queue, a frame starting.
  for (;;) {
    const std::int64_t done = busy_ ? on_bus_.end_ns : kNever;
    const std::int64_t host_write =
        host_.has_unwritten()
            ? std::max({host_.retry_ns, host_.packets.at(host_.written).submit_ns, clock_ns_})
            : kNever;
    const std::int64_t device_write = device_.has_unwritten() && !device_.tx.full()
                                          ? std::max(device_.packets.at(device_.written).submit_ns, clock_ns_)
                                          : kNever;
    std::int64_t start = kNever;
    if (!busy_ && (!host_.tx.empty() || !device_.tx.empty())) {
      std::int64_t first = kNever;
      if (!host_.tx.empty()) {
        first = host_.tx.front().submit_ns;
      }
      if (!device_.tx.empty()) {
        first = std::min(first, device_.tx.front().submit_ns);
      }
      start = std::max({bus_free_ns_, first, clock_ns_});
    }
    const std::int64_t next = std::min({done, host_write, device_write, start});
    if (next > until) {
      break;
    }
    clock_ns_ = next;
    if (next == done) {
      can_complete(sink);
    } else if (next == host_write) {
      can_write(host_, true, next);
    } else if (next == device_write) {
      can_write(device_, false, next);
    } else {
      can_start(next);
    }
  }
  clock_ns_ = std::max(clock_ns_, until);
}

void MockBus::restart_max_wait() noexcept {
  to_device_.max_wait_ns.store(0, std::memory_order_relaxed);
  to_host_.max_wait_ns.store(0, std::memory_order_relaxed);
}

void MockBus::reset() noexcept {
  to_device_waiting_.clear();
  to_host_waiting_.clear();
  to_device_lane_.next_slot = to_host_lane_.next_slot = 0;  // the next report takes its own frame
  for (CanNode* node : {&host_, &device_}) {
    node->packets.clear();
    node->tx.clear();
    node->written = node->next_frame = 0;
    node->retry_ns = node->backoff_ns = 0;
  }
  busy_ = false;
  host_codec_.reset();
  device_codec_.reset();
}

MockBusStats MockBus::stats() const noexcept {
  MockBusStats s;
  s.kind = options_.kind;
  const std::int64_t elapsed_ns =
      last_ns_.load(std::memory_order_relaxed) - start_ns_.load(std::memory_order_relaxed);
  s.elapsed_s = static_cast<double>(elapsed_ns) * 1e-9;
  const auto fill = [&](const Counters& c, MockBusDirection& out) {
    out.packets = c.packets.value();
    out.carried = c.carried.value();
    out.bytes = c.bytes.value();
    out.dropped = c.dropped.value();
    out.unsent = c.unsent.value();
    out.max_wait_s = static_cast<double>(c.max_wait_ns.load(std::memory_order_relaxed)) * 1e-9;
    if (s.elapsed_s <= 0.0) {
      return;
    }
    if (usb()) {
      out.load = static_cast<double>(out.bytes) / (s.elapsed_s * report_bytes_per_s_);
    } else if (can()) {
      out.load = static_cast<double>(c.busy_ns.load(std::memory_order_relaxed)) * 1e-9 / s.elapsed_s;
    }
  };
  fill(to_device_, s.host_to_device);
  fill(to_host_, s.device_to_host);
  s.enobufs = enobufs_.value();
  s.host_while_lagging = host_while_lagging_.value();
  return s;
}

std::optional<protocol::UsbInterruptSlots> declared_usb_slots(const MockBusOptions& bus) noexcept {
  if (bus.kind == MockBusKind::hid_hs) {
    return proto::UsbInterruptSlots{
        proto::kUsbHighSpeedMicroframe_s, proto::kUsbHighSpeedMaxReportsPerMicroframe,
        bus.usb_report_bytes == 0 ? proto::kUsbHighSpeedMaxReportBytes
                                  : std::clamp<std::size_t>(bus.usb_report_bytes, proto::kHidReportBytes,
                                                            proto::kUsbHighSpeedMaxReportBytes)};
  }
  if (bus.kind == MockBusKind::hid_fs) {
    return proto::kUsbFullSpeedSlots;
  }
  return std::nullopt;
}

std::optional<protocol::BusSpec> bus_spec_of(const MockBusOptions& bus) noexcept {
  protocol::BusSpec spec;
  switch (bus.kind) {
    case MockBusKind::none:
      return std::nullopt;
    case MockBusKind::hid_fs:
      return protocol::default_bus_spec(protocol::BusKind::hid_full_speed);
    case MockBusKind::hid_hs:
      return protocol::default_bus_spec(protocol::BusKind::hid_high_speed, false);
    case MockBusKind::can:
    case MockBusKind::canfd:
      spec = protocol::default_bus_spec(bus.kind == MockBusKind::can ? protocol::BusKind::can_classic
                                                                     : protocol::BusKind::can_fd);
      spec.nominal_bitrate_bit_per_s = bus.nominal_bitrate_bit_per_s;
      spec.data_bitrate_bit_per_s = bus.data_bitrate_bit_per_s;
      return spec;
  }
  return std::nullopt;
}

}  // namespace mrskin::sim
