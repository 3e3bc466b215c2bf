# Sourced by the scripts that render (test.sh, demo.sh, bench.sh): makes sure a Vulkan
# driver is there and wgpu uses it.
#
# - Installs Mesa's Vulkan drivers (lavapipe, a software rasteriser) and the Vulkan loader
#   when the loader is missing (Debian/Ubuntu, as root; otherwise it says what to install).
# - On a machine with no GPU device node, points the loader at lavapipe alone.
# - Sets WGPU_BACKEND=vulkan unless it is already set: without it a missing Vulkan driver
#   silently falls back to GL, which draws triangle strips wrongly.
lvp_icd=$(ls /usr/share/vulkan/icd.d/lvp_icd.*.json 2>/dev/null | head -n 1 || true)
if ! ldconfig -p 2>/dev/null | grep -q 'libvulkan\.so\.1' || [ -z "$lvp_icd" ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing mesa-vulkan-drivers and libvulkan1 (software Vulkan for rendering)"
    apt-get -o DPkg::Lock::Timeout=600 update -qq
    DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -qq \
      --no-install-recommends mesa-vulkan-drivers libvulkan1 >/dev/null
    lvp_icd=$(ls /usr/share/vulkan/icd.d/lvp_icd.*.json 2>/dev/null | head -n 1 || true)
  else
    echo "warning: no Vulkan driver found; install the packages mesa-vulkan-drivers and libvulkan1" >&2
  fi
fi
export WGPU_BACKEND="${WGPU_BACKEND:-vulkan}"
if [ -n "$lvp_icd" ] && ! ls /dev/dri/renderD* /dev/nvidia0 >/dev/null 2>&1; then
  export VK_DRIVER_FILES="$lvp_icd" VK_ICD_FILENAMES="$lvp_icd" NODEVICE_SELECT=1
fi
