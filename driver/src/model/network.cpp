// Implemented in this translation unit: see mrskin/driver/model/network.hpp.
