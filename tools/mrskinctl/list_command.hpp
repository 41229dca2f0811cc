// `mrskinctl list`: the MR skins reachable over hidraw, USB and the CAN interfaces that exist.
#pragma once

namespace mrskin::ctl {

struct ListOptions {
  bool json = false;
  bool probe = true;  // open each accessible unit briefly for its firmware and protocol version
};

// Exit code: kOk when at least one unit was found (even one that cannot be opened), kNoDevice
// when none was.
int cmd_list(const ListOptions& options);

}  // namespace mrskin::ctl
