#!/usr/bin/env bash
# Cargo runner for thumbv7em-none-eabihf (see .cargo/config.toml): boots the firmware ELF on
# QEMU's mps2-an386 (Cortex-M4F) and decodes its defmt log (semihosting → stdout) with
# defmt-print (`cargo install defmt-print`; without it the raw frames go to the terminal).
#
# UART0 (depth link) and UART1 (MAVLink) go to the chardevs in HARMONIC_FW_UART0 and
# HARMONIC_FW_UART1, default `null` (the firmware boots and waits for frames). For example
# HARMONIC_FW_UART0=tcp::4560,server=on,wait=off lets a camera side connect. The instruction
# counter is on (-icount shift=0: 1 ns of board time per instruction), so the tick counts the
# firmware logs are instruction counts / 40. Ctrl-C stops QEMU.
set -euo pipefail
elf="${1:?usage: qemu-run.sh FIRMWARE.elf}"
shift
qemu=(qemu-system-arm -machine mps2-an386 -cpu cortex-m4
      -display none -monitor none -nodefaults -nic none
      -icount shift=0,align=off
      -semihosting-config enable=on,target=native
      -serial "${HARMONIC_FW_UART0:-null}" -serial "${HARMONIC_FW_UART1:-null}"
      -kernel "$elf" "$@")
if command -v defmt-print >/dev/null 2>&1; then
  "${qemu[@]}" | defmt-print -e "$elf"
else
  echo "qemu-run.sh: defmt-print not found (cargo install defmt-print); raw defmt frames follow" >&2
  "${qemu[@]}"
fi
