// Range checks shared by every framing. Internal to the codec.
#pragma once

#include "mrskin/protocol/errors.hpp"
#include "mrskin/protocol/messages.hpp"

namespace mrskin::protocol::detail {

Error validate(const Message& message) noexcept;

}  // namespace mrskin::protocol::detail
