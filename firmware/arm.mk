# firmware/arm.mk - the STM32 firmware images (included from the top-level Makefile).
#
#   make firmware          build all four images and print their footprints
#   make arm-<image>       one image: arm-f103, arm-f4, arm-qemu-f1, arm-qemu-f4
#
# Images, each in build/arm/<image>/imubench.{elf,bin,hex,map}:
#   f103     STM32F103CB hardware (runs on a C8/RB too): 72 MHz (HSE 8 MHz x9), USART1 TX by DMA
#   f4       STM32F405/407 hardware: 168 MHz (HSE 8 MHz), FPU, USART1 TX by DMA
#   qemu-f1  the F1 board code for qemu-system-arm -M stm32vldiscovery (8 KiB RAM, 24 MHz,
#            polled TX, 128 KiB flash layout)
#   qemu-f4  the F4 board code for qemu-system-arm -M netduinoplus2 (168 MHz, polled TX)
# The QEMU images are the same sources with build-time settings (-D flags below,
# firmware/boards/common_arm/arm_board.h), not a separate firmware.
#
# Toolchain: Debian gcc-arm-none-eabi + libnewlib-arm-none-eabi (newlib-nano); the QEMU tests
# need qemu-system-arm. `make system-deps` (and so `make firmware` / `make test`) installs them.

SYSTEM_PKGS += gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm

ARM_CC      := arm-none-eabi-gcc
ARM_OBJCOPY := arm-none-eabi-objcopy
ARM_SIZE    := arm-none-eabi-size
ARM_BUILD   := $(BUILD)/arm
ARM_IMAGES  := f103 f4 qemu-f1 qemu-f4

# Build id sent in info.fw_build (15 characters at most reach the host).
ARM_BUILD_ID := $(shell git describe --always --dirty 2>/dev/null || echo unknown)

ARM_CFLAGS := -std=c11 -Os -g3 -Wall -Wextra -Werror -Wshadow -Wstrict-prototypes -Wdouble-promotion \
              -ffunction-sections -fdata-sections -fno-common -fstack-usage \
              -Ifirmware/core -Ifirmware/drivers -Ifirmware/boards/common_arm \
              '-DIB_BUILD_ID="$(ARM_BUILD_ID)"'
ARM_CFLAGS += $(EXTRA_CFLAGS)
ARM_LDFLAGS := -nostartfiles --specs=nano.specs --specs=nosys.specs -Wl,--gc-sections \
               -Wl,--no-warn-rwx-segments -Lfirmware/boards/common_arm

ARM_CPU_M3 := -mcpu=cortex-m3 -mthumb -mfloat-abi=soft
ARM_CPU_M4 := -mcpu=cortex-m4 -mthumb -mfpu=fpv4-sp-d16 -mfloat-abi=hard

# per image: chip directory, CPU flags, linker script, settings
ARM_CHIP_f103    := stm32f1
ARM_CPU_f103     := $(ARM_CPU_M3)
ARM_LD_f103      := firmware/boards/stm32f1/f103.ld
# -DIB_CRC32C_BYTEWISE=1: the one-table CRC-32C (1 KiB) rather than slicing-by-4 (4 KiB) in the
# F103's 24 KiB (firmware/core/crc32c.c)
ARM_DEFS_f103    := -DIB_CFG_QEMU=0 -DIB_CFG_TX_RING=1024 -DIB_CFG_RX_RING=256 -DIB_CRC32C_BYTEWISE=1

ARM_CHIP_qemu-f1 := stm32f1
ARM_CPU_qemu-f1  := $(ARM_CPU_M3)
ARM_LD_qemu-f1   := firmware/boards/stm32f1/qemu_f1.ld
ARM_DEFS_qemu-f1 := -DIB_CFG_QEMU=1 -DIB_CFG_QEMU_SYSCLK_HZ=24000000u -DIB_CFG_TX_RING=1024 -DIB_CFG_RX_RING=256 \
                    -DIB_CRC32C_BYTEWISE=1

ARM_CHIP_f4      := stm32f4
ARM_CPU_f4       := $(ARM_CPU_M4)
ARM_LD_f4        := firmware/boards/stm32f4/f4.ld
# -O2 (for speed) on the F4 image: 1 MiB of flash, and the calibrated 4 kHz stream's CPU
# budget (bench/arm_cycles.py) is tight; the F103 stays -Os for its 24 KiB flash budget.
ARM_OPT_f4       := -O2
ARM_DEFS_f4      := -DIB_CFG_QEMU=0 -DIB_CFG_HSE_HZ=8000000u -DIB_CFG_TX_RING=4096 -DIB_CFG_RX_RING=512

ARM_CHIP_qemu-f4 := stm32f4
ARM_CPU_qemu-f4  := $(ARM_CPU_M4)
ARM_LD_qemu-f4   := firmware/boards/stm32f4/qemu_f4.ld
ARM_DEFS_qemu-f4 := -DIB_CFG_QEMU=1 -DIB_CFG_QEMU_SYSCLK_HZ=168000000u -DIB_CFG_TX_RING=4096 -DIB_CFG_RX_RING=512

ARM_PORTABLE_SRC := $(wildcard firmware/core/*.c firmware/drivers/*.c)
ARM_COMMON_SRC   := $(wildcard firmware/boards/common_arm/*.c)

# The build id lives in a file rewritten only when it changes, so that a new commit (or a
# dirty tree) rebuilds the object that embeds it and nothing else.
ARM_BUILD_ID_FILE := $(ARM_BUILD)/build_id.txt
$(ARM_BUILD_ID_FILE): FORCE
	@mkdir -p $(@D)
	@echo '$(ARM_BUILD_ID)' | cmp -s - $@ || echo '$(ARM_BUILD_ID)' > $@

.PHONY: FORCE firmware firmware-size $(addprefix arm-,$(ARM_IMAGES))
FORCE:

# $(1) = image name
define ARM_IMAGE_RULES
ARM_SRC_$(1) := $$(ARM_PORTABLE_SRC) $$(ARM_COMMON_SRC) $$(wildcard firmware/boards/$$(ARM_CHIP_$(1))/*.c)
ARM_OBJ_$(1) := $$(patsubst %.c,$$(ARM_BUILD)/$(1)/obj/%.o,$$(ARM_SRC_$(1)))
ARM_FLAGS_$(1) := $$(ARM_CPU_$(1)) $$(ARM_CFLAGS) $$(ARM_OPT_$(1)) -Ifirmware/boards/$$(ARM_CHIP_$(1)) $$(ARM_DEFS_$(1))

$$(ARM_BUILD)/$(1)/obj/%.o: %.c
	@mkdir -p $$(@D)
	@$$(ARM_CC) $$(ARM_FLAGS_$(1)) -MMD -MP -c $$< -o $$@

$$(ARM_BUILD)/$(1)/obj/firmware/boards/common_arm/arm_board.o: $$(ARM_BUILD_ID_FILE)

$$(ARM_BUILD)/$(1)/imubench.elf: $$(ARM_OBJ_$(1)) $$(ARM_LD_$(1)) firmware/boards/common_arm/sections.ld
	@$$(ARM_CC) $$(ARM_CPU_$(1)) $$(ARM_LDFLAGS) -T$$(ARM_LD_$(1)) \
	    -Wl,-Map=$$(ARM_BUILD)/$(1)/imubench.map $$(ARM_OBJ_$(1)) -lm -o $$@

$$(ARM_BUILD)/$(1)/imubench.bin: $$(ARM_BUILD)/$(1)/imubench.elf
	@$$(ARM_OBJCOPY) -O binary $$< $$@

$$(ARM_BUILD)/$(1)/imubench.hex: $$(ARM_BUILD)/$(1)/imubench.elf
	@$$(ARM_OBJCOPY) -O ihex $$< $$@

arm-$(1): $$(ARM_BUILD)/$(1)/imubench.elf $$(ARM_BUILD)/$(1)/imubench.bin $$(ARM_BUILD)/$(1)/imubench.hex

-include $$(ARM_OBJ_$(1):.o=.d)
endef

$(foreach i,$(ARM_IMAGES),$(eval $(call ARM_IMAGE_RULES,$(i))))

# Footprint: text = code + constants (+ .data's initial values in flash: add data),
# data = initialised RAM, bss = zeroed RAM + the stack (a NOLOAD section, see sections.ld).
firmware-size: $(addprefix arm-,$(ARM_IMAGES))
	@echo "firmware footprints (flash = text + data, RAM = data + bss; bss includes the stack):"
	@$(ARM_SIZE) $(foreach i,$(ARM_IMAGES),$(ARM_BUILD)/$(i)/imubench.elf)

firmware: system-deps
	@$(MAKE) --no-print-directory firmware-size
