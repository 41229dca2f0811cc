// Replays every file of tests/fuzz/corpus/<decoder>/ (protocol decoders and stream sources; the
// text parsers' corpora have no entry function here) through the fuzzers' entry functions,
// with any compiler. A crash, a sanitizer report (in the debug preset) or a broken
// invariant fails the test. Another corpus root (with the same sub-folders) replays with
//   MRSKIN_FUZZ_CORPUS_DIR=/some/corpus build/release/tests/fuzz/mrskin_fuzz_corpus_replay
#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <iterator>
#include <string>
#include <vector>

#include "fuzz_entry.hpp"
#include "fuzz_sources.hpp"

namespace {

namespace fs = std::filesystem;
using Entry = const char* (*)(const std::uint8_t*, std::size_t);

fs::path corpus_root() {
  if (const char* dir = std::getenv("MRSKIN_FUZZ_CORPUS_DIR")) {
    return dir;
  }
  return MRSKIN_FUZZ_CORPUS_DIR;
}

std::vector<std::uint8_t> read_file(const fs::path& path);

void replay(const std::string& decoder, Entry entry) {
  const fs::path dir = corpus_root() / decoder;
  ASSERT_TRUE(fs::is_directory(dir)) << dir;
  std::size_t files = 0;
  for (const auto& item : fs::recursive_directory_iterator(dir)) {
    if (!item.is_regular_file()) {
      continue;
    }
    // Exactly sized heap copy, so a sanitizer build sees reads past the end.
    const std::vector<std::uint8_t> bytes = read_file(item.path());
    const char* failure = entry(bytes.data(), bytes.size());
    EXPECT_EQ(failure, nullptr) << item.path() << ": " << (failure != nullptr ? failure : "");
    ++files;
  }
  EXPECT_GT(files, 0U) << "empty corpus " << dir;
  std::cout << decoder << ": replayed " << files << " files\n";
}

TEST(ProtocolFuzzCorpus, Packet) { replay("packet", mrskin::fuzz::packet_entry); }
TEST(ProtocolFuzzCorpus, CanClassic) { replay("can_classic", mrskin::fuzz::can_classic_entry); }
TEST(ProtocolFuzzCorpus, CanFd) { replay("can_fd", mrskin::fuzz::can_fd_entry); }
TEST(ProtocolFuzzCorpus, Quantize) { replay("quantize", mrskin::fuzz::quantize_entry); }
TEST(SourcesFuzzCorpus, Igtl) { replay("igtl", mrskin::fuzz::igtl_entry); }
TEST(SourcesFuzzCorpus, Udp) { replay("udp", mrskin::fuzz::udp_entry); }

std::vector<std::uint8_t> read_file(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  const std::vector<char> raw((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  return {raw.begin(), raw.end()};
}

// The seeds made from the golden vectors (make_seeds.py) decode: the harness formats and
// the seeds agree, so the fuzzers start from inputs that reach the message parsers.
TEST(ProtocolFuzzCorpus, GoldenSeedsDecode) {
  namespace p = mrskin::protocol;
  const fs::path root = MRSKIN_FUZZ_CORPUS_DIR;
  for (const char* name : {"heartbeat", "valve_currents", "telemetry", "identity", "status_hid_report"}) {
    const auto bytes = read_file(root / "packet" / name);
    EXPECT_EQ(p::decode_packet(bytes).error, p::Error::ok) << name;
  }
  EXPECT_EQ(p::decode_packet(read_file(root / "packet" / "version2_heartbeat")).error,
            p::Error::wrong_version);
  for (const char* name : {"valve_currents", "telemetry", "identity", "management"}) {
    const auto bytes = read_file(root / "can_classic" / name);
    ASSERT_GE(bytes.size(), 13U) << name;
    p::CanDecoder decoder(mrskin::fuzz::decoder_node(bytes[0]));
    int complete = 0;
    for (std::size_t pos = 1; pos + 12 <= bytes.size(); pos += 12) {
      p::CanFrame f;
      f.id = static_cast<std::uint32_t>(bytes[pos + 1] | (bytes[pos + 2] << 8U));
      f.length = bytes[pos + 3];
      std::copy_n(bytes.begin() + static_cast<std::ptrdiff_t>(pos + 4), 8, f.data.begin());
      const p::CanDecoded d = decoder.decode(f);
      EXPECT_EQ(d.error, p::Error::ok) << name;
      complete += d.complete ? 1 : 0;
    }
    EXPECT_GE(complete, 1) << name;
  }
}

// The valid seeds (make_seeds.py) parse: the seeds reach the body parsers and the sample checks.
TEST(SourcesFuzzCorpus, ValidSeedsParse) {
  namespace src = mrskin::bridge::sources;
  const fs::path root = MRSKIN_FUZZ_CORPUS_DIR;
  for (const char* name : {"sensor_1", "sensor_3_mN", "sensor_6", "transform", "position", "qtdata", "tdata",
                           "ndarray_f32", "ndarray_u16", "v2_transform", "stream"}) {
    const auto bytes = read_file(root / "igtl" / name);
    std::size_t used = 0;
    int messages = 0;
    for (;;) {
      const auto f = src::next_igtl_frame(std::span(bytes).subspan(used), 65536);
      if (f.status != src::IgtlFrame::Status::complete) {
        break;
      }
      const auto m = src::open_igtl_message(
          f.header, std::span(bytes).subspan(used + src::kIgtlHeaderBytes, f.header.body_bytes));
      ASSERT_EQ(m.fault, src::IgtlFault::none) << name;
      src::IgtlFault body = src::IgtlFault::none;
      switch (m.kind) {
        case src::IgtlKind::force:
          body = src::parse_igtl_sensor(m.content, mrskin::bridge::SourceOptions{}.robot_to_tissue).fault;
          break;
        case src::IgtlKind::pose:
          body = src::parse_igtl_pose(f.header.type, m.content, "*").fault;
          break;
        case src::IgtlKind::map:
          body = src::parse_igtl_pressure_map(m.content, 2e-3).fault;
          break;
      }
      EXPECT_EQ(body, src::IgtlFault::none) << name;
      used += f.bytes;
      ++messages;
    }
    EXPECT_EQ(used, bytes.size()) << name;
    EXPECT_GE(messages, 1) << name;
  }
  const auto udp = read_file(root / "udp" / "valid");
  EXPECT_TRUE(src::parse_udp_datagram(udp, udp.size()).ok);
}

// Inputs that have no file: empty and one-byte inputs go through every entry.
TEST(ProtocolFuzzCorpus, TinyInputs) {
  for (const Entry entry :
       {mrskin::fuzz::packet_entry, mrskin::fuzz::can_classic_entry, mrskin::fuzz::can_fd_entry,
        mrskin::fuzz::quantize_entry, mrskin::fuzz::igtl_entry, mrskin::fuzz::udp_entry}) {
    EXPECT_EQ(entry(nullptr, 0), nullptr);
    for (unsigned b = 0; b < 256; ++b) {
      const auto byte = static_cast<std::uint8_t>(b);
      EXPECT_EQ(entry(&byte, 1), nullptr);
    }
  }
}

}  // namespace
