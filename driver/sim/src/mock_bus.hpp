// The mock's bus model (MockBusOptions, mock_device.hpp): packets in, the same packets out at the
// time the bus delivers them, or dropped. Private to libmrskin_sim: mock_bus.cpp defines it.
// Everything runs on the thread that steps the unit (the host's in synchronous mode); the
// counters are read from any thread. Preallocated: no allocation after construction.
#pragma once

#include <array>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/relaxed_counter.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/driver/transports/can.hpp"
#include "mrskin/protocol/bus_budget.hpp"
#include "mrskin/sim/mock_device.hpp"

namespace mrskin::sim {

// Where the bus hands what it carried.
class __attribute__((visibility("hidden"))) BusSink {
 public:
  BusSink() = default;
  virtual ~BusSink() = default;
  BusSink(const BusSink&) = delete;
  BusSink& operator=(const BusSink&) = delete;
  BusSink(BusSink&&) = delete;
  BusSink& operator=(BusSink&&) = delete;
  virtual void deliver_to_device(const Datagram& d, TimePoint at) noexcept = 0;
  virtual void deliver_to_host(const Datagram& d, TimePoint at) noexcept = 0;
};

// A fixed-capacity FIFO.
template <class T>
class __attribute__((visibility("hidden"))) BusRing {
 public:
  explicit BusRing(std::size_t capacity) : items_(capacity == 0 ? 1 : capacity), capacity_(capacity) {}
  [[nodiscard]] std::size_t size() const noexcept { return size_; }
  [[nodiscard]] bool empty() const noexcept { return size_ == 0; }
  [[nodiscard]] bool full() const noexcept { return size_ >= capacity_; }
  [[nodiscard]] std::size_t room() const noexcept { return capacity_ - size_; }
  T& at(std::size_t i) noexcept { return items_[(head_ + i) % items_.size()]; }
  [[nodiscard]] const T& at(std::size_t i) const noexcept { return items_[(head_ + i) % items_.size()]; }
  T& front() noexcept { return at(0); }
  // Callers check full() first.
  T& push() noexcept { return items_[(head_ + size_++) % items_.size()]; }
  void pop() noexcept {
    head_ = (head_ + 1) % items_.size();
    --size_;
  }
  void clear() noexcept { head_ = size_ = 0; }

 private:
  std::vector<T> items_;
  std::size_t capacity_;
  std::size_t head_ = 0;
  std::size_t size_ = 0;
};

class __attribute__((visibility("hidden"))) MockBus {
 public:
  explicit MockBus(const MockBusOptions& options);

  // The unit's first step: the bus runs from t, the epoch of its loads. Before it the link is
  // ideal and not counted: a synchronous mock's handshake runs before its clock starts, and
  // nothing would carry the bus's delayed packets there.
  void start(TimePoint t) noexcept;
  // A packet the host's transport hands to the bus at t, and one the unit sends at t. Neither
  // advances the bus (a packet that finds the bus free may be delivered at once); advance() does.
  void host_sent(const Datagram& d, TimePoint t, BusSink& sink) noexcept;
  void device_sent(const Datagram& d, TimePoint t, BusSink& sink) noexcept;
  // A host packet that reached a lagging unit: delivered at t outside the bus and its loads, and
  // counted (MockBusStats::host_while_lagging), unless host packets still wait on the bus (then
  // host_sent, so that none overtakes another).
  void host_sent_while_lagging(const Datagram& d, TimePoint t, BusSink& sink) noexcept;
  // USB: whether a report the unit hands over at t goes out in t's frame (its slot free, none
  // booked ahead of it). True on the other buses and before the unit's first step.
  [[nodiscard]] bool device_slot_free(TimePoint t) const noexcept;
  // Runs the bus up to t: delivers, in time order, what it finished carrying by then.
  void advance(TimePoint t, BusSink& sink) noexcept;
  // The link went down: whatever was queued is gone.
  void reset() noexcept;
  // The longest waits count from now on (a daemon's loop, not its open's configuration reads).
  // Any thread.
  void restart_max_wait() noexcept;
  [[nodiscard]] MockBusStats stats() const noexcept;
  [[nodiscard]] MockBusKind kind() const noexcept { return options_.kind; }
  // The latest time the bus has been told of (sent or advanced to): it never runs back.
  [[nodiscard]] TimePoint latest_time() const noexcept {
    return TimePoint{std::chrono::nanoseconds(last_ns_.load(std::memory_order_relaxed))};
  }

 private:
  struct Counters {
    RelaxedCounter packets;
    RelaxedCounter carried;
    RelaxedCounter bytes;
    RelaxedCounter dropped;
    RelaxedCounter unsent;
    std::atomic<std::int64_t> max_wait_ns{0};
    std::atomic<std::int64_t> busy_ns{0};  // CAN
    void waited(std::int64_t ns) noexcept;
    void carry(const Datagram& report) noexcept;  // USB: one report, its packets and bytes
  };
  // USB: one direction's interrupt endpoint. Slot k*R + r is report r of frame k.
  struct UsbLane {
    std::int64_t next_slot = 0;
  };
  struct Waiting {  // a report that waits for its slot
    TimePoint due{};
    TimePoint submitted{};
    Datagram datagram{};
    std::int32_t telemetry_block = -1;  // telemetry only: its first sensor (telemetry_block_of)
  };
  // CAN
  struct FrameInfo {
    std::uint32_t id = 0;
    std::uint8_t data_bytes = 0;
    bool fd = false;
    // The frame that completes a packet: its bytes [packet_begin, packet_end) in the datagram
    // (a packed report on classic CAN delivers each packet when its own last frame ends).
    std::uint16_t packet_begin = 0;
    std::uint16_t packet_end = 0;  // 0: completes none
  };
  struct CanPacket {
    Datagram datagram{};
    std::int64_t submit_ns = 0;
    std::array<FrameInfo, CanPacketCodec::kMaxFrames> frames{};
    std::size_t frame_count = 0;
    std::size_t unsent = 0;  // its packets with no form on the framing (classic echoes)
  };
  struct QueuedFrame {
    FrameInfo frame{};
    std::int64_t submit_ns = 0;
    bool last = false;  // the last frame of its packet
  };
  // One node's side: its packets (those whose frames are all written first, then the one being
  // written, then those waiting), and its queue of frames for the bus.
  struct CanNode {
    CanNode(std::size_t packets_capacity, std::size_t frames_capacity)
        : packets(packets_capacity), tx(frames_capacity) {}
    BusRing<CanPacket> packets;
    std::size_t written = 0;     // packets at the front whose frames are all in tx or sent
    std::size_t next_frame = 0;  // of the packet being written
    BusRing<QueuedFrame> tx;
    std::int64_t retry_ns = 0;    // host: after ENOBUFS, the next write attempt
    std::int64_t backoff_ns = 0;  // host: doubles while ENOBUFS lasts
    [[nodiscard]] bool has_unwritten() const noexcept { return written < packets.size(); }
  };
  struct OnBus {
    QueuedFrame frame{};
    bool from_host = false;
    std::int64_t end_ns = 0;
  };

  [[nodiscard]] bool usb() const noexcept;
  [[nodiscard]] bool can() const noexcept;
  // The slot a report handed over at t gets: false when the queue before it is full.
  bool usb_schedule(UsbLane& lane, TimePoint t, TimePoint& due) const noexcept;
  // A report handed to a USB lane at t: delivered now (its frame's slot is free and none waits),
  // waiting for a later slot, or dropped (usb_queue_reports already wait). Counted.
  enum class UsbPlace : unsigned char { now, later, dropped };
  UsbPlace usb_place(UsbLane& lane, BusRing<Waiting>& waiting, Counters& counters, const Datagram& d,
                     TimePoint t) const noexcept;
  void usb_device_sent(const Datagram& d, TimePoint t, BusSink& sink) noexcept;
  void can_device_sent(const Datagram& d, TimePoint t) noexcept;
  [[nodiscard]] std::int64_t frame_ns(const FrameInfo& f) const noexcept;
  bool encode(CanPacketCodec& codec, const Datagram& d, CanPacket& out) noexcept;
  // One packet's frames appended to out; false when the codec refuses it.
  bool encode_packet_frames(CanPacketCodec& codec, const Datagram& d, std::size_t begin, std::size_t end,
                            CanPacket& out) noexcept;
  // Writes the node's frames into its queue while there is room: the host's transport gets
  // ENOBUFS past it and backs off; the unit feeds its queue as frames leave it.
  void can_write(CanNode& node, bool host, std::int64_t t_ns) noexcept;
  void can_start(std::int64_t t_ns) noexcept;
  void can_complete(BusSink& sink) noexcept;
  void note_time(std::int64_t t_ns) noexcept;
  void note_handshake(const Datagram& d, CanRole sender) noexcept;

  MockBusOptions options_;
  // USB
  std::int64_t interval_ns_ = 1'000'000;
  std::size_t reports_per_interval_ = 1;
  double report_bytes_per_s_ = 64'000.0;
  UsbLane to_device_lane_;
  TimePoint host_last_{};  // the latest time a host packet was handed over
  UsbLane to_host_lane_;
  BusRing<Waiting> to_device_waiting_;
  BusRing<Waiting> to_host_waiting_;
  // Telemetry: the unit keeps one sample waiting; a newer one takes its place (and its slot).
  // CAN
  CanPacketCodec host_codec_;
  CanPacketCodec device_codec_;
  CanPacketCodec trial_codec_;  // device_codec_'s copy for a trial encode
  CanNode host_;
  CanNode device_;
  std::int64_t backoff_min_ns_ = 0;
  std::int64_t backoff_max_ns_ = 0;
  OnBus on_bus_{};
  bool busy_ = false;
  std::int64_t bus_free_ns_ = 0;
  std::int64_t clock_ns_ = 0;  // the bus's own time: what it has run up to
  CanPacket scratch_{};
  std::array<protocol::CanFrame, CanPacketCodec::kMaxFrames> frames_{};
  // Statistics
  Counters to_device_;
  Counters to_host_;
  RelaxedCounter enobufs_;
  RelaxedCounter host_while_lagging_;
  std::atomic<std::int64_t> start_ns_{0};
  std::atomic<std::int64_t> last_ns_{0};
  bool started_ = false;
};

// The bus the model stands for, as the bus budget sees it (docs/protocol.md, "Bus budget"):
// nullopt for none (an ideal link); hid-hs with 64-byte reports, what a host assumes until the unit
// declares its reports (1.2's UsbSlots, which the session's budget then takes).
std::optional<protocol::BusSpec> bus_spec_of(const MockBusOptions& bus) noexcept;
// The reports a unit on this USB bus declares in 1.2's UsbSlots (hid_fs: full speed; hid_hs: 3 a
// microframe of usb_report_bytes); nullopt on CAN and on the ideal link.
std::optional<protocol::UsbInterruptSlots> declared_usb_slots(const MockBusOptions& bus) noexcept;

}  // namespace mrskin::sim
