// Entry logic of the stream sources' fuzzers (igtl, udp), shared by the libFuzzer targets
// (fuzz_igtl.cpp, fuzz_udp.cpp) and the corpus replay test. As in fuzz_entry.hpp, every entry
// returns nullptr when the parser behaved, or a short description of the broken invariant.
//
// Input formats (docs/reliability.md, section "Fuzzing"):
//   igtl: a TCP byte stream of OpenIGTLink messages, as igtl:// receives it. It is parsed as it
//         is, then again with the CRC-64 of every complete message made right (so the bodies are
//         reached without solving the CRC).
//   udp:  one datagram, as udp:// receives it; then again with its CRC-32C made right.
// Bodies, contents and datagrams are parsed from exactly sized heap copies, so ASan reports any
// read past them.
#pragma once

#include <igtl_util.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <span>
#include <string_view>
#include <vector>

#include "core.hpp"
#include "igtl_parse.hpp"
#include "udp_source.hpp"

namespace mrskin::fuzz {

namespace src = mrskin::bridge::sources;

// ---- OpenIGTLink --------------------------------------------------------------------------

inline std::vector<std::uint8_t> exact_copy(std::span<const std::uint8_t> bytes) {
  return {bytes.begin(), bytes.end()};
}

inline std::uint32_t be32(const std::uint8_t* p) noexcept {
  return (std::uint32_t{p[0]} << 24U) | (std::uint32_t{p[1]} << 16U) | (std::uint32_t{p[2]} << 8U) | p[3];
}

// The float32 a pose parser should have read at offset at, compared as such (NaN equals NaN).
inline bool same_f32(double parsed, const std::uint8_t* p) noexcept {
  float f = 0.0F;
  const std::uint32_t bits = be32(p);
  std::memcpy(&f, &bits, sizeof f);
  return (std::isnan(parsed) && std::isnan(f)) || parsed == static_cast<double>(f);
}

inline const char* check_igtl_sensor(std::span<const std::uint8_t> content) noexcept {
  using F = src::IgtlFault;
  const std::vector<std::uint8_t> c = exact_copy(content);
  const std::array<double, 9> identity{1, 0, 0, 0, 1, 0, 0, 0, 1};
  const std::array<double, 9> tilted{0.0, 0.6, 0.8, 1.0, 0.0, 0.0, 0.0, 0.8, -0.6};  // a rotation
  const src::IgtlForce f = src::parse_igtl_sensor(c, identity);
  if (f.fault != F::none && f.fault != F::sensor_length && f.fault != F::sensor_count &&
      f.fault != F::sensor_unit && f.fault != F::non_finite) {
    return "SENSOR: a fault that is not a SENSOR's";
  }
  if (src::parse_igtl_sensor(c, tilted).fault != f.fault) return "SENSOR: the frame changes the verdict";
  const bool fits = c.size() >= 10 && c[0] != 0 && c.size() == 10 + 8 * std::size_t{c[0]};
  if ((f.fault == F::sensor_length) == fits) return "SENSOR: length refused or accepted wrongly";
  if (f.fault == F::sensor_length) return nullptr;
  if (f.values != c[0]) return "SENSOR: value count is not the body's";
  const bool count_ok = f.values == 1 || f.values == 3 || f.values == 6;
  if ((f.fault == F::sensor_count) == count_ok) return "SENSOR: value count refused or accepted wrongly";
  if (f.fault == F::none && !std::isfinite(f.normal_N)) return "SENSOR: accepted a force that is not finite";
  return nullptr;
}

inline const char* check_igtl_pose(std::string_view type, std::span<const std::uint8_t> content) noexcept {
  using F = src::IgtlFault;
  const std::vector<std::uint8_t> c = exact_copy(content);
  const bool tracking = type == "QTDATA" || type == "TDATA";
  for (const std::string_view tool : {std::string_view("*"), std::string_view("Stylus")}) {
    const src::IgtlPosition p = src::parse_igtl_pose(type, c, tool);
    if (p.fault != F::none && p.fault != F::pose_length && p.fault != F::no_tool) {
      return "pose: a fault that is not a pose's";
    }
    if (p.fault == F::no_tool && (!tracking || tool == "*")) return "pose: no tool where any is taken";
    if (p.fault != F::none) continue;
    std::size_t at = 0;
    if (type == "TRANSFORM") {
      if (c.size() != 48) return "TRANSFORM: accepted a body of another size";
      at = 36;
    } else if (type == "POSITION") {
      if (c.size() != 12 && c.size() != 24 && c.size() != 28)
        return "POSITION: accepted a body of another size";
    } else {
      const std::size_t element =
          type == "TDATA" ? src::kIgtlTdataElementBytes : src::kIgtlQtdataElementBytes;
      if (c.empty() || c.size() % element != 0) return "QTDATA/TDATA: accepted a body of another size";
      if (tool != "*") continue;  // the first element's pose is checked below
      at = src::kIgtlTrackNameBytes + 2 + (type == "TDATA" ? 36 : 0);
    }
    if (!same_f32(p.x_mm, c.data() + at) || !same_f32(p.y_mm, c.data() + at + 4) ||
        !same_f32(p.z_mm, c.data() + at + 8)) {
      return "pose: the position is not the one at its offset";
    }
  }
  return nullptr;
}

inline const char* check_igtl_map(std::span<const std::uint8_t> content) noexcept {
  using F = src::IgtlFault;
  constexpr double kPitch_m = 2e-3;
  const std::vector<std::uint8_t> c = exact_copy(content);
  const src::IgtlPressureMap m = src::parse_igtl_pressure_map(c, kPitch_m);
  if (m.fault != F::none && m.fault != F::map_type && m.fault != F::map_length &&
      m.fault != F::map_oversized && m.fault != F::non_finite) {
    return "NDARRAY: a fault that is not an NDARRAY's";
  }
  if (m.fault == F::map_oversized && m.rows * m.cols <= src::kIgtlMaxMapCells) {
    return "NDARRAY: a small map called oversized";
  }
  if (m.fault != F::none) return nullptr;
  if (m.dims != 2 || m.rows == 0 || m.cols == 0 || m.rows * m.cols > src::kIgtlMaxMapCells) {
    return "NDARRAY: accepted a map of bad sizes";
  }
  const std::size_t cells = m.rows * m.cols;
  const std::size_t element = c.size() < 6 ? 0 : (c.size() - 6) / cells;
  if ((element != 1 && element != 2 && element != 4 && element != 8) || c.size() != 6 + cells * element) {
    return "NDARRAY: accepted a body that does not fit its sizes";
  }
  if (std::isnan(m.force_N) || m.force_N < 0.0) return "NDARRAY: a force that is negative or NaN";
  if (std::isfinite(m.force_N)) {
    // The centroid is a weighted mean of the cells' offsets: inside the array.
    const double half_x_m = 0.5 * static_cast<double>(m.cols - 1) * kPitch_m;
    const double half_y_m = 0.5 * static_cast<double>(m.rows - 1) * kPitch_m;
    if (!std::isfinite(m.dx_m) || !std::isfinite(m.dy_m) ||
        std::fabs(m.dx_m) > half_x_m * (1 + 1e-9) + 1e-12 ||
        std::fabs(m.dy_m) > half_y_m * (1 + 1e-9) + 1e-12) {
      return "NDARRAY: the contact lies outside the array";
    }
  }
  return nullptr;
}

inline const char* check_igtl_message(const src::IgtlHeader& h,
                                      std::span<const std::uint8_t> bytes) noexcept {
  using F = src::IgtlFault;
  const std::vector<std::uint8_t> body = exact_copy(bytes);
  const src::IgtlMessage m = src::open_igtl_message(h, body);
  const bool version_ok = h.version == 1 || h.version == 2;
  const bool pose_type =
      h.type == "TRANSFORM" || h.type == "POSITION" || h.type == "QTDATA" || h.type == "TDATA";
  const bool known_type = h.type == "SENSOR" || pose_type || h.type == "NDARRAY";
  if ((m.fault == F::version) == version_ok) return "message: header version refused or accepted wrongly";
  if (m.fault != F::none && m.fault != F::version && m.fault != F::crc && m.fault != F::extended_header &&
      m.fault != F::type) {
    return "message: a fault that is not a message's";
  }
  if (m.fault == F::type && known_type) return "message: a type it reads refused";
  if (m.fault == F::none) {
    // NOLINTNEXTLINE(cppcoreguidelines-pro-type-const-cast): crc64 only reads
    if (crc64(const_cast<std::uint8_t*>(body.data()), body.size(), 0) != h.crc) {
      return "message: accepted a body that does not match its CRC";
    }
    if (!known_type) return "message: accepted a type it does not read";
    const bool inside =
        m.content.empty() ||
        (m.content.data() >= body.data() && m.content.data() + m.content.size() <= body.data() + body.size());
    if (!inside) return "message: content outside its body";
    if (h.version == 1 && (m.content.data() != body.data() || m.content.size() != body.size())) {
      return "message: version 1 content is not the whole body";
    }
    const src::IgtlKind expected = h.type == "SENSOR" ? src::IgtlKind::force
                                   : pose_type        ? src::IgtlKind::pose
                                                      : src::IgtlKind::map;
    if (m.kind != expected) return "message: the kind is not its type's";
    const std::int64_t ns = h.timestamp != 0 ? src::igtl_timestamp_ns(h.timestamp) : 0;
    if (!src::stamp_ok(ns)) return "message: a timestamp outside 0..2^62 ns";
    switch (m.kind) {
      case src::IgtlKind::force:
        if (const char* f = check_igtl_sensor(m.content)) return f;
        break;
      case src::IgtlKind::pose:
        if (const char* f = check_igtl_pose(h.type, m.content)) return f;
        break;
      case src::IgtlKind::map:
        if (const char* f = check_igtl_map(m.content)) return f;
        break;
    }
  }
  // Every body parser takes any bytes, whatever the header says.
  if (const char* f = check_igtl_sensor(body)) return f;
  for (const std::string_view type : {"TRANSFORM", "POSITION", "QTDATA", "TDATA"}) {
    if (const char* f = check_igtl_pose(type, body)) return f;
  }
  return check_igtl_map(body);
}

// Frames and checks every message of a stream as the source's session loop does; with fix_crc,
// first sets each complete message's CRC-64 (bytes 50..57 of its header) to its body's.
inline const char* check_igtl_stream(std::vector<std::uint8_t>& stream, bool fix_crc) noexcept {
  constexpr std::size_t kMaxBodyBytes = 65536;  // SourceOptions::max_message_bytes
  std::size_t used = 0;
  for (;;) {
    const std::span<std::uint8_t> rest(stream.data() + used, stream.size() - used);
    const src::IgtlFrame f = src::next_igtl_frame(rest, kMaxBodyBytes);
    switch (f.status) {
      case src::IgtlFrame::Status::incomplete:
        if (rest.size() >= src::kIgtlHeaderBytes && f.header.body_bytes <= kMaxBodyBytes &&
            rest.size() >= src::kIgtlHeaderBytes + f.header.body_bytes) {
          return "frame: a complete message called incomplete";
        }
        return nullptr;
      case src::IgtlFrame::Status::oversized:
        if (rest.size() < src::kIgtlHeaderBytes || f.header.body_bytes <= kMaxBodyBytes) {
          return "frame: oversized without a header announcing a large body";
        }
        return nullptr;  // the source closes the connection
      case src::IgtlFrame::Status::complete:
        break;
    }
    if (f.header.body_bytes > kMaxBodyBytes || f.bytes != src::kIgtlHeaderBytes + f.header.body_bytes ||
        f.bytes > rest.size()) {
      return "frame: a complete message that does not fit the stream";
    }
    const std::span<std::uint8_t> body = rest.subspan(src::kIgtlHeaderBytes, f.header.body_bytes);
    src::IgtlHeader h = f.header;
    if (fix_crc) {
      h.crc = crc64(body.data(), body.size(), 0);
      for (std::size_t i = 0; i < 8; ++i) {
        rest[50 + i] = static_cast<std::uint8_t>(h.crc >> (56U - 8U * i));
      }
      h = src::parse_igtl_header(rest.data());
    }
    if (const char* failure = check_igtl_message(h, body)) return failure;
    used += f.bytes;
  }
}

inline const char* igtl_entry(const std::uint8_t* data, std::size_t size) noexcept {
  std::vector<std::uint8_t> stream(data, data + size);
  if (const char* f = check_igtl_stream(stream, false)) return f;
  return check_igtl_stream(stream, true);
}

// ---- UDP ----------------------------------------------------------------------------------

inline const char* check_udp(std::span<const std::uint8_t> bytes, std::size_t length) noexcept {
  using bridge::DropReason;
  const std::vector<std::uint8_t> d = exact_copy(bytes);
  const src::UdpParsed p = src::parse_udp_datagram(d, length);
  if (length > bridge::kUdpDatagramBytes) {
    return !p.ok && p.reason == DropReason::oversized ? nullptr : "UDP: an oversized datagram not refused so";
  }
  if (length < bridge::kUdpDatagramBytes || d.size() < bridge::kUdpDatagramBytes) {
    return !p.ok && p.reason == DropReason::length ? nullptr : "UDP: a short datagram not refused so";
  }
  const bool format_ok = std::memcmp(d.data(), "MRSS", 4) == 0 && d[4] == bridge::kUdpVersion && d[5] == 0;
  if (!format_ok)
    return !p.ok && p.reason == DropReason::format ? nullptr : "UDP: a foreign datagram not refused";
  if (!p.ok)
    return p.reason == DropReason::crc ? nullptr : "UDP: a sample refused for no reason of its format";
  // Accepted: the sample re-encodes to the datagram (flags and reserved bytes aside: sent as 0).
  const auto again = bridge::encode_udp_sample(p.sample);
  const bool spare_zero = d[6] == 0 && d[7] == 0 && d[12] == 0 && d[13] == 0 && d[14] == 0 && d[15] == 0;
  for (std::size_t i = 0; i < 64; ++i) {
    if ((i < 6 || (i >= 8 && i < 12) || i >= 16) && again.at(i) != d[i])
      return "UDP: the sample re-encodes to other bytes";
  }
  if (spare_zero && !std::equal(again.begin(), again.end(), d.begin()))
    return "UDP: the sample re-encodes with another CRC";
  // What the source then takes: finite values in range.
  static src::AtomicStats stats;
  static src::SourceEvents events;
  const bridge::SourceOptions o;
  bridge::SlaveSample s;
  s.force_N = p.sample.force_N;
  s.indentation_m = p.sample.indentation_m;
  s.contact_x_m = p.sample.contact_x_m;
  s.contact_y_m = p.sample.contact_y_m;
  s.tip_radius_m = p.sample.tip_radius_m;
  if (src::values_ok(s, o, stats, events)) {
    const std::array<double, 5> v{s.force_N, s.indentation_m, s.contact_x_m, s.contact_y_m, s.tip_radius_m};
    if (!std::all_of(v.begin(), v.end(), [](double x) { return std::isfinite(x); })) {
      return "UDP: a sample with NaN or Inf taken";
    }
    if (s.force_N < 0.0 || s.force_N > o.max_force_N ||
        std::fabs(s.indentation_m) > o.max_abs_indentation_m ||
        std::fabs(s.contact_x_m) > o.max_abs_contact_m || std::fabs(s.contact_y_m) > o.max_abs_contact_m ||
        s.tip_radius_m < 0.0 || s.tip_radius_m > o.max_tip_radius_m) {
      return "UDP: a sample out of range taken";
    }
  }
  return nullptr;
}

inline const char* udp_entry(const std::uint8_t* data, std::size_t size) noexcept {
  const std::span<const std::uint8_t> d(data, size);
  if (const char* f = check_udp(d, size)) return f;
  // Longer than the receive buffer: the source hands over the bytes it got and the real length.
  if (size > bridge::kUdpDatagramBytes) {
    if (const char* f = check_udp(d.first(size - 1), size)) return f;
  }
  if (size == bridge::kUdpDatagramBytes) {
    std::vector<std::uint8_t> fixed(data, data + size);
    const std::uint32_t crc = bridge::crc32c(std::span(fixed).first(64));
    std::memcpy(fixed.data() + 64, &crc, sizeof crc);  // little-endian, as the format
    if (const char* f = check_udp(fixed, size)) return f;
  }
  return nullptr;
}

}  // namespace mrskin::fuzz
