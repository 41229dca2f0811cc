// Links the installed mrskin::driver and prints the versions it reports.
#include <iostream>

#include "mrskin/driver/version.hpp"

int main() {
  std::cout << "mrskin library " << mrskin::library_version() << ", protocol v"
            << mrskin::protocol_version_major() << '.' << mrskin::protocol_version_minor() << '\n';
  return 0;
}
