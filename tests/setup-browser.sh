#!/usr/bin/env bash
# The real headless browser the tests of the people's pages drive (tests/ros/test_people_browser.py): Debian's
# chromium and chromium-driver (/usr/bin/chromedriver). Installed here, with apt, never downloaded at run time;
# without them that test skips, saying so. Run by .ci/run and `make setup-browser` (needs root or sudo).
set -euo pipefail
if command -v chromium >/dev/null && [ -x /usr/bin/chromedriver ]; then
  exit 0
fi
SUDO=""
[ "$(id -u)" = 0 ] || SUDO=sudo
$SUDO apt-get install -y -q chromium chromium-driver >/dev/null 2>&1 ||
  ($SUDO apt-get update -q >/dev/null 2>&1 && $SUDO apt-get install -y -q chromium chromium-driver >/dev/null 2>&1) ||
  echo "tests/setup-browser.sh: chromium could not be installed: tests/ros/test_people_browser.py will skip" >&2
