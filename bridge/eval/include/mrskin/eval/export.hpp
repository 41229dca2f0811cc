#pragma once

// libmrskin_eval is built with hidden visibility: a symbol is part of its ABI only when its
// declaration carries MRSKIN_EVAL_API (docs/api.md, "ABI and SONAME"). ELF needs the same
// attribute when building and when using the library.
#define MRSKIN_EVAL_API __attribute__((visibility("default")))
