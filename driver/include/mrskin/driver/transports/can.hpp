// can://IFACE?node=N[&fd=1]: raw SocketCAN, classic CAN (8-byte frames) or CAN FD.
//   can://can0?node=3        classic CAN, node id 3 (1..15)
//   can://vcan0?node=5&fd=1  one CAN FD frame per packet (the interface needs MTU 72)
// The session speaks protocol-v1 packets; CanPacketCodec turns them into frames and back
// (docs/protocol.md, "Classic CAN" and "CAN FD"). Every socket call goes through the
// CanSocketApi seam (driver/src/transports/can_socket_api.hpp, not installed), so the
// transport's logic is tested with a fake bus.
//
// Back-pressure instead of ENOBUFS: the socket's send buffer is the kernel's minimum, so a
// loaded bus makes write() wait (EAGAIN, then POLLOUT) with few frames in flight; an ENOBUFS
// anyway (the interface's queue full) keeps the frame and retries it after a short backoff.
// Meanwhile the datagrams queue up to send_queue, then send() answers would_block.
// Error frames are counted; bus-off makes the state bus_off until the controller restarts.
// An interface that goes down makes it disconnected; it reopens by itself when it is back.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "mrskin/driver/clock.hpp"
#include "mrskin/driver/enumerate.hpp"
#include "mrskin/driver/export.hpp"
#include "mrskin/driver/transport.hpp"
#include "mrskin/protocol/can.hpp"
#include "mrskin/protocol/packet.hpp"

namespace mrskin {

struct CanUri {
  std::string interface;  // 1..15 characters, as `ip link` names it
  std::uint8_t node = 0;  // 1..15
  bool fd = false;
};
// Throws InvalidArgument naming the bad part.
MRSKIN_DRIVER_API CanUri parse_can_uri(std::string_view uri);
// "can://can0?node=3" or "can://can0?node=3&fd=1".
MRSKIN_DRIVER_API std::string format_can_uri(const CanUri& uri);

// --- packets <-> frames ----------------------------------------------------------------------
// host: sends host->device packets, receives device->host frames (the transport).
// device: the other way round (a simulated node on a bus, the VM tests).
enum class CanRole : std::uint8_t { host, device };

// Converts the packets one side of a link sends into frames, and the frames of the other
// side back into packets, for one node. Allocation-free; one instance per direction pair
// and thread.
//  - Classic CAN: ValveCurrents and Telemetry go as 4-value blocks. A message that does not
//    start on a block boundary (the session sends 27 currents a packet) fills the rest of its
//    first block from the values last sent, which the codec keeps (64 per node). Telemetry
//    goes as a TimeSync frame followed by its sensor blocks, all with one rolling counter;
//    the receiving codec stamps each block with that time and hands it on as one Telemetry
//    packet (first = 4 x block), and drops blocks whose TimeSync it did not see. CellTargets
//    go one frame per cell, Status, Heartbeat and StateRequest as single frames, identity
//    and configuration as segmented transfers. There is no Heartbeat echo on classic CAN:
//    the device role sends none.
//  - Classic CAN between two 1.2 sides (protocol 1.2's delta blocks, docs/protocol.md): a block
//    goes only when its values changed, or every kCanDeltaRefreshUpdates updates, or (host) when
//    the whole update repeats the last (a refresh). The codec learns both sides' versions from the
//    handshake it carries (IdentifyRequest, Identity); a 1.1 side gets every block.
//  - CAN FD: one frame per packet, the packet's bytes and sequence unchanged.
//  - Packets from CAN FD frames keep the peer's sequence. On classic CAN every packet handed
//    on (single frames and segmented transfers alike) is numbered by the codec: one more
//    than the last, plus the loss it knows of (the samples or statuses a rolling-counter gap
//    skipped, or one for a frame that failed its CRC or a block without its TimeSync), so
//    the session's gap counter sees it.
class MRSKIN_DRIVER_API CanPacketCodec {
 public:
  // Frames one packet may need: a 64-byte segmented packet (10), 27 currents off a block
  // boundary (8 blocks), a TimeSync and 7 sensor blocks.
  static constexpr std::size_t kMaxFrames = protocol::kCanMaxFramesPerMessage;
  // Values a node addresses in blocks: 16 blocks of 4.
  static constexpr std::size_t kBlockValues = protocol::kCanMaxBlocks * protocol::kCanValuesPerBlock;

  CanPacketCodec(CanRole role, std::uint8_t node, bool fd) noexcept;

  struct Encoded {
    protocol::Error error = protocol::Error::ok;
    std::size_t frames = 0;  // 0 with ok: nothing to send on this framing (a classic echo)
    std::size_t unsent = 0;  // packets with no form on this framing (classic heartbeat echoes)
  };
  // A packet this role sends -> frames. unknown_type for a message of the other direction,
  // out_of_range for a valve, sensor or cell this framing cannot address. A packed report
  // (protocol 1.2, several packets): on CAN FD one frame carrying it (encode_canfd_report); on
  // classic CAN each packet's frames in order, exactly as if sent one by one (too_long past
  // kMaxFrames). Any packet's error refuses the whole report.
  Encoded encode(std::span<const std::uint8_t> packet,
                 std::span<protocol::CanFrame, kMaxFrames> out) noexcept;
  // Whether encode() would take the packet or packed report (encodes it with a scratch codec;
  // keeps no state). Safe on any thread.
  [[nodiscard]] static protocol::Error check(CanRole role, bool fd,
                                             std::span<const std::uint8_t> packet) noexcept;

  struct Decoded {
    protocol::Error error = protocol::Error::ok;  // wrong_node, bad_crc, unknown_type (other direction)...
    bool complete = false;                        // packet holds one packet to hand on
    Datagram packet{};
  };
  // A frame from the other side. Frames that are not for this node and role give an error
  // and change nothing but the loss accounting of this node's own frames.
  Decoded decode(const protocol::CanFrame& frame) noexcept;

  // Forgets transfers, counters, the TimeSync and the peer's version (the link was lost); keeps
  // the values last sent, and sends every block at the next update.
  void reset() noexcept;

  // A packet or report that `sender` sent and this codec neither encoded nor decoded (the mock's
  // bus carries packets whole): the handshake's versions, which decide delta blocks. encode() and
  // decode() note their own.
  void note_handshake(std::span<const std::uint8_t> packet, CanRole sender) noexcept;
  // Whether cyclic blocks go as deltas now (classic CAN, both sides 1.2).
  [[nodiscard]] bool delta_blocks() const noexcept;

  [[nodiscard]] CanRole role() const noexcept { return role_; }
  [[nodiscard]] std::uint8_t node() const noexcept { return node_; }
  [[nodiscard]] bool fd() const noexcept { return fd_; }

 private:
  // One decoded packet's frames, into out (classic: blocks, single or segmented frames).
  Encoded encode_one(const protocol::PacketDecoded& p, std::span<protocol::CanFrame> out) noexcept;
  Encoded encode_blocks(const protocol::Message& message, std::span<protocol::CanFrame> out) noexcept;
  [[nodiscard]] protocol::ValveCurrents valve_block(std::size_t start, std::uint8_t values) const noexcept;
  [[nodiscard]] protocol::Telemetry sensor_block(std::size_t start, std::uint8_t values) const noexcept;
  static void finish(Decoded& d, const protocol::Message& message, std::uint8_t sequence) noexcept;
  void note_handshake(const protocol::Message& message, bool own) noexcept;

  CanRole role_;
  std::uint8_t node_;
  bool fd_;
  protocol::CanDecoder decoder_;
  // Rolling counters of what this side sends, per frame kind.
  std::uint8_t tx_blocks_ = 0;  // valve blocks (host) or TimeSync + sensor blocks (device)
  std::uint8_t tx_cells_ = 0;
  std::uint8_t tx_heartbeat_ = 0;
  std::uint8_t tx_state_ = 0;                         // state requests (host) or status (device)
  std::array<std::uint16_t, kBlockValues> shadow_{};  // values last sent, for partial blocks
  // The versions each side declared in the handshake (0.0: not seen yet).
  std::uint8_t own_major_ = 0;
  std::uint8_t own_minor_ = 0;
  std::uint8_t peer_major_ = 0;
  std::uint8_t peer_minor_ = 0;
  protocol::CanDeltaBlocks delta_;
  // Receiving side.
  std::uint8_t rx_sequence_ = 0;                 // next number for a packet rebuilt from a single frame
  std::uint32_t lost_ = 0;                       // losses seen since the last packet handed on
  protocol::CounterTracker sample_counter_{16};  // TimeSync (host) or valve blocks (device)
  protocol::CounterTracker status_counter_{16};  // Status (host) or StateRequest (device)
  bool have_time_ = false;
  std::uint8_t time_counter_ = 0;
  std::uint32_t time_us_ = 0;
};

// Identifier filters (CAN_RAW_FILTER) for the frames a role receives for a node: exact
// standard data frames, blocks with any block number.
struct CanIdFilter {
  std::uint32_t id = 0;
  std::uint32_t mask = 0;
};
struct CanIdFilters {
  std::array<CanIdFilter, 8> filters{};
  std::size_t count = 0;
};
MRSKIN_DRIVER_API CanIdFilters can_receive_filters(CanRole role, std::uint8_t node) noexcept;

// --- the transport -----------------------------------------------------------------------------
struct CanTransportOptions {
  CanRole role = CanRole::host;  // device: a simulated node's end (VM tests)
  // Multiplies the durations below (slow environments, VMs).
  double time_scale = 1.0;
  // Between reopen attempts while the interface is down or gone, doubling from min to max.
  Duration reopen_backoff_min = std::chrono::milliseconds(10);
  Duration reopen_backoff_max = std::chrono::milliseconds(500);
  // After ENOBUFS, the frame is written again after this, doubling up to max while it lasts.
  Duration enobufs_backoff_min = std::chrono::microseconds(100);
  Duration enobufs_backoff_max = std::chrono::milliseconds(5);
  std::size_t send_queue = 64;       // datagrams
  std::size_t receive_queue = 1024;  // datagrams
};

// Opens the socket (filters, error frames, FD frames, minimal send buffer), binds it to the
// interface and starts its I/O thread. Throws InvalidArgument (bad URI; fd=1 on an interface
// whose MTU is not 72: says how to raise it), DeviceNotFound (no such interface: lists those
// that exist and how to create one; interface down: the command that brings it up; a kernel
// without CAN: says so, and that modprobe can_raw loads it), PermissionDenied, Error.
MRSKIN_DRIVER_API std::unique_ptr<Transport> open_can_transport(std::string_view uri,
                                                                const CanTransportOptions& options = {});

// What the CAN transport counted beyond TransportCounters. Any thread.
struct CanTransportStats {
  std::uint64_t frames_written = 0;
  std::uint64_t frames_read = 0;       // every frame read, errors and foreign ones included
  std::uint64_t enobufs = 0;           // writes refused with ENOBUFS, then retried
  std::uint64_t send_buffer_full = 0;  // writes refused with EAGAIN, retried on POLLOUT
  std::uint64_t foreign_frames = 0;    // frames of other nodes or of our own direction
  // Datagrams not written: no frame form on this framing (a classic heartbeat echo), or a
  // write error. Once all are out, counters().sent + dropped_packets = datagrams send() took,
  // unless a link loss or bus-off discarded some.
  std::uint64_t dropped_packets = 0;
};
// nullopt when transport does not come from open_can_transport().
MRSKIN_DRIVER_API std::optional<CanTransportStats> can_transport_stats(const Transport& transport) noexcept;

}  // namespace mrskin
