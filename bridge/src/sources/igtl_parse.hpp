// OpenIGTLink framing and bodies as igtl:// reads them, without I/O: defined in igtl.cpp, used by
// its I/O thread and by the fuzzer (tests/fuzz/fuzz_igtl.cpp). Private to the bridge library.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string_view>

namespace mrskin::bridge::sources {

inline constexpr std::size_t kIgtlHeaderBytes = 58;
inline constexpr std::size_t kIgtlMaxMapCells = 4096;  // 64 x 64
// QTDATA and TDATA: elements of a 20-byte name, type, reserved, then the pose.
inline constexpr std::size_t kIgtlTrackNameBytes = 20;
inline constexpr std::size_t kIgtlQtdataElementBytes =
    50;                                                    // name, type, reserved, position[3], quaternion[4]
inline constexpr std::size_t kIgtlTdataElementBytes = 70;  // name, type, reserved, transform[12]

struct IgtlHeader {
  std::uint16_t version = 0;
  std::string_view type;  // views into the header's bytes
  std::string_view device;
  std::uint64_t timestamp = 0;  // 32.32 fixed point seconds; 0: none
  std::uint64_t body_bytes = 0;
  std::uint64_t crc = 0;
};
// p holds at least kIgtlHeaderBytes.
[[nodiscard]] IgtlHeader parse_igtl_header(const std::uint8_t* p) noexcept;
[[nodiscard]] std::int64_t igtl_timestamp_ns(std::uint64_t timestamp) noexcept;
// A fixed-width, NUL-padded field.
[[nodiscard]] std::string_view igtl_field(const std::uint8_t* p, std::size_t n) noexcept;

// The message at the front of a stream's bytes. oversized: its body exceeds max_body_bytes, so the
// framing past it cannot be trusted.
struct IgtlFrame {
  enum class Status : unsigned char { incomplete, oversized, complete };
  Status status = Status::incomplete;
  IgtlHeader header;      // unless incomplete
  std::size_t bytes = 0;  // header and body, when complete
};
[[nodiscard]] IgtlFrame next_igtl_frame(std::span<const std::uint8_t> stream,
                                        std::size_t max_body_bytes) noexcept;

// Why a message or a body is dropped (each comment: its DropReason).
enum class IgtlFault : unsigned char {
  none,
  version,          // format: header version not 1 or 2
  crc,              // crc
  extended_header,  // length: a version 2 extended header that does not fit the body
  type,             // type: not a type this source reads
  sensor_length,    // length
  sensor_count,     // length: not 1, 3 or 6 values
  sensor_unit,      // unit: not newtons
  non_finite,       // non_finite: a SENSOR value or an NDARRAY cell
  pose_length,      // length
  no_tool,          // device: no QTDATA/TDATA element of the wanted name
  map_type,         // type: not a 2-D array of a real scalar type
  map_length,       // length
  map_oversized,    // oversized: more than kIgtlMaxMapCells cells
};

enum class IgtlKind : unsigned char { force, pose, map };  // SENSOR; TRANSFORM...TDATA; NDARRAY

struct IgtlMessage {
  IgtlFault fault = IgtlFault::none;
  IgtlKind kind = IgtlKind::force;
  std::span<const std::uint8_t> content;  // what a version 1 body holds, inside the body
};
// Checks the header version, the CRC-64 and a version 2 extended header, in that order, then the type.
[[nodiscard]] IgtlMessage open_igtl_message(const IgtlHeader& h, std::span<const std::uint8_t> body) noexcept;

struct IgtlForce {
  IgtlFault fault = IgtlFault::none;
  std::size_t values = 0;  // as the body declares it
  double normal_N = 0.0;   // along the tissue's outward normal; < 0 pulls
};
// SENSOR content: larray u8, status u8, unit u64, larray x float64 (1: the normal force; 3: a force
// vector in the robot's frame; 6: a wrench, force first).
[[nodiscard]] IgtlForce parse_igtl_sensor(std::span<const std::uint8_t> content,
                                          const std::array<double, 9>& robot_to_tissue) noexcept;

struct IgtlPosition {
  IgtlFault fault = IgtlFault::none;
  double x_mm = 0.0;  // in the robot's frame, as sent (NaN and Inf included)
  double y_mm = 0.0;
  double z_mm = 0.0;
};
// TRANSFORM: 12 float32, the translation last; POSITION: 3 float32 then an optional quaternion;
// QTDATA, TDATA: the element named tool ("*": the first).
[[nodiscard]] IgtlPosition parse_igtl_pose(std::string_view type, std::span<const std::uint8_t> content,
                                           std::string_view tool) noexcept;

struct IgtlPressureMap {
  IgtlFault fault = IgtlFault::none;
  std::uint8_t scalar_type = 0;
  std::size_t dims = 0;
  std::size_t rows = 0;
  std::size_t cols = 0;
  double force_N = 0.0;  // sum(max(p, 0)) x pitch^2
  double dx_m = 0.0;     // pressure-weighted centroid from the array's centre
  double dy_m = 0.0;
};
// NDARRAY content: type u8, dim u8, dim x u16 sizes, then the elements row-major; pressures in Pa.
[[nodiscard]] IgtlPressureMap parse_igtl_pressure_map(std::span<const std::uint8_t> content,
                                                      double pitch_m) noexcept;

}  // namespace mrskin::bridge::sources
