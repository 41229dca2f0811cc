// Classic CAN (8 bytes, 11-bit identifiers) and CAN FD framing of protocol v1.
//
// Identifier: bits 10..8 function, bits 7..4 block, bits 3..0 node (1..15).
//   function 0 management: block 0 heartbeat (host->device), 1 status, 2 time sync,
//              3 state request (host->device), 4 segmented host->device,
//              5 segmented device->host
//   function 1 valve-current block (host->device), 4 values of valves 4*block..
//   function 2 sensor block (device->host), 4 values of sensors 4*block..
//   function 3 cell target (host->device), block = cell index bits 3..0
//   function 4 CAN FD packet host->device, function 5 CAN FD packet device->host
// Single frames are always 8 bytes: [0..5] payload, [6] rolling counter (high nibble) and
// value count or zero (low nibble), [7] CRC-8/SAE-J1850 over id_hi, id_lo, bytes 0..6.
// Identity and configuration travel as packets split ISO-TP style (single, first and
// consecutive frames, no flow control in v1) on the segmented identifiers.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>

#include "mrskin/protocol/errors.hpp"
#include "mrskin/protocol/export.hpp"
#include "mrskin/protocol/messages.hpp"
#include "mrskin/protocol/packet.hpp"

namespace mrskin::protocol {

struct CanFrame {
  std::uint32_t id = 0;  // 11-bit identifier
  std::uint8_t length = 0;
  bool fd = false;
  std::array<std::uint8_t, 64> data{};
  bool operator==(const CanFrame&) const = default;
};

enum class CanFunction : std::uint8_t {
  management = 0,
  valve_block = 1,
  sensor_block = 2,
  cell_target = 3,
  fd_host_to_device = 4,
  fd_device_to_host = 5,
};
enum class CanManagement : std::uint8_t {
  heartbeat = 0,
  status = 1,
  time_sync = 2,
  state_request = 3,
  segmented_host_to_device = 4,
  segmented_device_to_host = 5,
};

inline constexpr std::uint8_t kCanNodeMin = 1;
inline constexpr std::uint8_t kCanNodeMax = 15;
inline constexpr std::size_t kCanValuesPerBlock = 4;
inline constexpr std::size_t kCanMaxBlocks = 16;
inline constexpr std::size_t kCanMaxFramesPerMessage = 12;  // 64-byte packet segmented

constexpr std::uint32_t can_id(CanFunction f, std::uint8_t block, std::uint8_t node) noexcept {
  return (static_cast<std::uint32_t>(f) << 8U) | (static_cast<std::uint32_t>(block & 0xFU) << 4U) |
         (node & 0xFU);
}

enum class Direction : std::uint8_t { host_to_device, device_to_host };

struct CanEncodeResult {
  Error error = Error::ok;
  std::size_t frames = 0;
};

// Encodes one message into classic CAN frames for node. Cyclic messages become one frame
// per block (ValveCurrents and Telemetry need first % 4 == 0; Telemetry's device time goes
// in a separate TimeSync frame that the caller sends first). Identity and configuration
// are packets segmented over several frames; sequence numbers their packet.
MRSKIN_PROTOCOL_API CanEncodeResult encode_can(const Message& message, std::uint8_t node,
                                               std::uint8_t counter, std::uint8_t sequence,
                                               std::span<CanFrame> out) noexcept;

// Encodes a message as one CAN FD frame carrying a packet.
MRSKIN_PROTOCOL_API CanEncodeResult encode_canfd(const Message& message, std::uint8_t node,
                                                 Direction direction, std::uint8_t sequence,
                                                 CanFrame& out) noexcept;

// Protocol 1.2: one CAN FD frame carrying a packed report (packed_report.hpp): the report's
// packets, each checked with decode_packet (the first error is returned and nothing written),
// zero padded to the next CAN FD length. The walk ends at the report's first 0x00 or its end.
MRSKIN_PROTOCOL_API CanEncodeResult encode_canfd_report(std::span<const std::uint8_t> report,
                                                        std::uint8_t node, Direction direction,
                                                        CanFrame& out) noexcept;

// Protocol 1.2, classic CAN: delta blocks (docs/protocol.md, "Delta blocks (1.2)"). Between two
// 1.2 peers the sender of a cyclic update (valve blocks, host to device; sensor blocks with their
// TimeSync, device to host) sends a block only when one of its values differs from those last
// sent, or when the block went unsent for kCanDeltaRefreshUpdates - 1 updates, so that a lost
// frame heals within kCanDeltaRefreshUpdates updates (inside the 16-value rolling counter). The
// host sends currents at will, so its update equal in every value to the last one is a refresh
// and goes whole (the bridge's resend of unchanged currents): a host's update always carries a
// block. The unit sends a sample every period: a quiet sample sends only its due blocks, after
// its TimeSync. The frames keep 1.1's layout; only which of them go changes.
inline constexpr std::size_t kCanDeltaRefreshUpdates = 10;
inline constexpr std::uint8_t kCanDeltaBlocksMinor = 2;

// Whether a peer that declared major.minor in the handshake reads delta blocks.
constexpr bool reads_delta_blocks(std::uint8_t major, std::uint8_t minor) noexcept {
  return major == kVersionMajor && minor >= kCanDeltaBlocksMinor;
}

// The sender's side of delta blocks for one kind of block (a node's 16 blocks of 4 values).
// Pure arithmetic, no allocation.
class MRSKIN_PROTOCOL_API CanDeltaBlocks {
 public:
  static constexpr std::size_t kValues = kCanMaxBlocks * kCanValuesPerBlock;
  // repeat_refreshes: an update equal to the last goes whole (the host's valve blocks); false for
  // the unit's sensor blocks.
  explicit CanDeltaBlocks(bool repeat_refreshes) noexcept : repeat_refreshes_(repeat_refreshes) {}
  // The blocks [first_block, end_block) of an update whose values (all 64, as the sender now
  // holds them) are values: bit b of the result is set for each block to send. Records what
  // goes as sent. end_block <= 16 and first_block < end_block, else 0.
  std::uint16_t select(std::span<const std::uint16_t, kValues> values, std::size_t first_block,
                       std::size_t end_block) noexcept;
  // Every block goes at its next update (a new link, a new handshake).
  void reset() noexcept { unsent_updates_.fill(kNeverSent); }

 private:
  static constexpr std::uint8_t kNeverSent = 0xFF;
  bool repeat_refreshes_;
  std::array<std::uint16_t, kValues> sent_{};
  std::array<std::uint8_t, kCanMaxBlocks> unsent_updates_ = [] {
    std::array<std::uint8_t, kCanMaxBlocks> a{};
    a.fill(kNeverSent);
    return a;
  }();
};

struct CanDecoded {
  Error error = Error::ok;
  bool complete = false;      // a message is ready (false while a segmented transfer runs)
  std::uint8_t counter = 0;   // rolling counter of a single frame
  std::uint8_t sequence = 0;  // packet sequence of a segmented or FD message
  std::uint8_t peer_version = 0;
  Message message{};
};

// Decodes frames addressed to one node; keeps the state of one segmented transfer per
// direction. No allocation; frames for other nodes give wrong_node. A CAN FD frame gives its
// first packet; a receiver that agreed on packed reports walks the frame's data (PacketWalker).
class MRSKIN_PROTOCOL_API CanDecoder {
 public:
  explicit CanDecoder(std::uint8_t node) noexcept : node_(node) {}
  CanDecoded decode(const CanFrame& frame) noexcept;

 private:
  struct Reassembly {
    std::array<std::uint8_t, kPacketMaxBytes> buffer{};
    std::size_t expected = 0;
    std::size_t received = 0;
    std::uint8_t next_index = 0;
    bool active = false;
  };
  static CanDecoded decode_segment(const CanFrame& frame, Reassembly& r) noexcept;
  std::uint8_t node_;
  std::array<Reassembly, 2> reassembly_{};
};

// Bits on the wire of a classic or FD data frame (11-bit id) with worst-case stuffing,
// including interframe space. Classic 8-byte frame: 135 bits.
MRSKIN_PROTOCOL_API std::size_t can_frame_bits_worst_case(std::size_t data_bytes, bool fd) noexcept;

// can_frame_bits_worst_case split by the bit rate each part is sent at. Classic: every bit at
// the nominal rate. FD with bit-rate switch: SOF to BRS with its worst-case stuff bits, then ACK,
// EOF and intermission at the nominal rate (17 + 4 + 12 = 33 bits); ESI to the CRC delimiter at
// the data rate.
struct CanFrameBits {
  std::size_t nominal_bits = 0;
  std::size_t data_bits = 0;
};
MRSKIN_PROTOCOL_API CanFrameBits can_frame_bits_by_phase_worst_case(std::size_t data_bytes, bool fd) noexcept;
// Time a data frame holds the bus with worst-case stuffing, interframe space included, s.
// Classic frames are sent at nominal_bitrate_bit_per_s throughout; FD frames switch to
// data_bitrate_bit_per_s for their data phase. Pure arithmetic: the mock's bus model and a bus
// budget use the same figure.
MRSKIN_PROTOCOL_API double can_frame_time_worst_case_s(std::size_t data_bytes, bool fd,
                                                       double nominal_bitrate_bit_per_s,
                                                       double data_bitrate_bit_per_s) noexcept;

}  // namespace mrskin::protocol
