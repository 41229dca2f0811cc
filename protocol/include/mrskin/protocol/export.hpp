#pragma once

// libmrskin_protocol is built with hidden visibility: a symbol is part of its ABI only when its
// declaration carries MRSKIN_PROTOCOL_API (docs/api.md, "ABI and SONAME"). ELF needs the same
// attribute when building and when using the library.
#define MRSKIN_PROTOCOL_API __attribute__((visibility("default")))
