// SPDX-License-Identifier: GPL-2.0
/*
 * magvec_vspi: a virtual SPI controller whose only device answers like a TI ADS131M04 front end
 * (frame format: drivers/codecs/include/magvec/drivers/ads131m04.hpp, behaviour as
 * drivers/sim SimAds131Device). It exists so that the project's spidev driver can be tested on a
 * real kernel (VM system tests): the device is created with the modalias "dh2228fv",
 * which the built-in spidev driver binds to, giving /dev/spidev0.0. A second device (chip select
 * 1, /dev/spidev0.1) is a plain loopback (rx = tx) for tests of the transfer path itself.
 *
 * Frames are 18 bytes: response word (16 bit + pad), 4 channel words (24 bit, two's complement),
 * CRC-16-CCITT (poly 0x1021, seed 0xFFFF) over the first 15 bytes. The response to a command
 * appears in the next frame: RESET -> FF24h, WREG -> 010a aaaa ammm mmmm, anything else (NULL)
 * -> STATUS (WLENGTH 24 bit, DRDY0..3 set, RESET as MODE.RESET).
 * RESET, as the datasheet's register map has it: STATUS.RESET (bit 10) reads MODE.RESET (bit 10),
 * which a reset sets (MODE reset value 0510h) and only a WREG of MODE with that bit 0 clears.
 * Reading the reset acknowledge (FF24h) or writing another register leaves it set, so a driver
 * that never clears MODE.RESET sees every data frame flagged as after a reset. A reset puts
 * GAIN1 and MODE back to their defaults; inject_reset (writable) does that before the next frame,
 * as a brown-out or a glitch on SYNC/RESET would mid-stream.
 * Every data frame (answer to NULL) is a new conversion n = 0, 1, 2, ...: a field rotating by
 * one degree per conversion,
 *   ch0 = fixp_cos32(n) >> 9, ch1 = fixp_sin32(n) >> 9, ch2 = 0x100000, ch3 = n mod 2^23,
 * so a reader can check values and detect lost or repeated frames (ch3).
 * Feed (daemon end-to-end test): while /dev/magvec_adc_feed is open, the device answers with
 * conversions written there instead: each 16-byte record (4 x s32, native endianness: ch0..3
 * codes) is one conversion, queued in a FIFO of FEED_DEPTH; each data frame takes the oldest with
 * STATUS.DRDY0..3 set; with the FIFO empty it repeats the last one with DRDY clear (not new data).
 * A FIFO (not the real ADC's single result latch) keeps conversion k paired with the k-th data
 * frame when the reader runs late under emulation, so the test judges the daemon, not the VM's
 * scheduling. A full FIFO refuses the write (-ENOSPC). Closing the feed returns to the pattern.
 * What the FIFO hides is counted: fed_overruns (data frames read while a newer conversion was
 * already queued: conversions the real device's single latch would have lost), fed_max_queued.
 * Fault injection: with crc_error_every = N > 0, every Nth data frame has one data byte flipped
 * after its CRC was computed (writable at run time in /sys/module/magvec_vspi/parameters/).
 */
#include <linux/bug.h> /* fixp-arith.h uses BUG_ON without including it */
#include <linux/fixp-arith.h>
#include <linux/miscdevice.h>
#include <linux/module.h>
#include <linux/platform_device.h>
#include <linux/spi/spi.h>
#include <linux/spinlock.h>
#include <linux/uaccess.h>

#define FRAME_BYTES 18
#define RESET_RESPONSE 0xFF24
#define STATUS_RESET 0x0400
#define STATUS_WLENGTH24 0x0100
#define STATUS_DRDY 0x000F
#define REG_MODE 0x02
#define REG_GAIN1 0x04
#define MODE_RESET 0x0400
#define MODE_RESET_VALUE 0x0510

static unsigned int crc_error_every;
module_param(crc_error_every, uint, 0644);
MODULE_PARM_DESC(crc_error_every, "corrupt every Nth data frame after its CRC (0 = never)");
static unsigned int data_frames;
module_param(data_frames, uint, 0444);
MODULE_PARM_DESC(data_frames, "data frames (conversions) sent");
static unsigned int crc_errors_injected;
module_param(crc_errors_injected, uint, 0444);
MODULE_PARM_DESC(crc_errors_injected, "data frames sent with a corrupted byte");
static unsigned int fed_conversions;
module_param(fed_conversions, uint, 0444);
MODULE_PARM_DESC(fed_conversions, "conversions written to /dev/magvec_adc_feed");
static unsigned int fed_frames;
module_param(fed_frames, uint, 0444);
MODULE_PARM_DESC(fed_frames, "data frames that carried a fed conversion as new data");
/* A real ADS131M04 holds one conversion: a data frame read after the next conversion was already
 * queued behind it is a conversion that device would have overwritten (lost). */
static unsigned int fed_overruns;
module_param(fed_overruns, uint, 0444);
MODULE_PARM_DESC(fed_overruns, "data frames read while a newer fed conversion was already queued");
static unsigned int fed_max_queued;
module_param(fed_max_queued, uint, 0444);
MODULE_PARM_DESC(fed_max_queued, "most fed conversions queued at once");
static unsigned int gain1;
module_param(gain1, uint, 0444);
MODULE_PARM_DESC(gain1, "GAIN1 register as last written by WREG");
static unsigned int mode = MODE_RESET_VALUE;
module_param(mode, uint, 0444);
MODULE_PARM_DESC(mode, "MODE register (bit 10 RESET: set by a reset, cleared only by a WREG)");
static unsigned int inject_reset;
module_param(inject_reset, uint, 0644);
MODULE_PARM_DESC(inject_reset,
                 "write 1: the device resets (registers to defaults) before the next frame");
static unsigned int resets;
module_param(resets, uint, 0444);
MODULE_PARM_DESC(resets, "device resets (RESET commands and injected ones)");

static struct platform_device* vspi_pdev;
static struct spi_controller* vspi_ctlr;
static struct spi_device* vspi_dev;
static struct spi_device* vspi_loop;

/* Device state; only touched from transfer_one, which the SPI core serialises. */
static u16 pending_response;
static bool pending_is_status = true;

/* Feed state (written by user space, read by transfer_one): feed_lock. */
static DEFINE_SPINLOCK(feed_lock);
static atomic_t feed_open = ATOMIC_INIT(0);
#define FEED_DEPTH 256
static bool feed_active;
static s32 feed_fifo[FEED_DEPTH][4];
static unsigned int feed_head; /* oldest */
static unsigned int feed_count;
static s32 feed_last[4]; /* the last conversion served */

static u16 crc16_ccitt(const u8* p, size_t n) {
  u16 crc = 0xFFFF;
  int bit;

  while (n--) {
    crc ^= (u16)(*p++) << 8;
    for (bit = 0; bit < 8; ++bit)
      crc = (crc & 0x8000) ? (u16)((crc << 1) ^ 0x1021) : (u16)(crc << 1);
  }
  return crc;
}

static void put16(u8* p, u16 v) {
  p[0] = v >> 8;
  p[1] = v & 0xFF;
  p[2] = 0;
}

static void put24(u8* p, s32 v) {
  u32 u = (u32)v & 0xFFFFFF;

  p[0] = u >> 16;
  p[1] = (u >> 8) & 0xFF;
  p[2] = u & 0xFF;
}

static void device_reset(void) {
  mode = MODE_RESET_VALUE;
  gain1 = 0;
  ++resets;
}

static void build_frame(u8* out) {
  bool data = pending_is_status;
  u16 response = pending_response;
  u32 n = data_frames;
  s32 codes[4];
  u16 drdy = STATUS_DRDY;
  unsigned long flags;
  bool fed;

  spin_lock_irqsave(&feed_lock, flags);
  fed = feed_active;
  if (fed) {
    if (feed_count > 0) {
      memcpy(codes, feed_fifo[feed_head], sizeof(codes));
      if (data) {
        if (feed_count > 1) ++fed_overruns;
        memcpy(feed_last, codes, sizeof(codes));
        feed_head = (feed_head + 1) % FEED_DEPTH;
        --feed_count;
        ++fed_frames;
      }
    } else {
      memcpy(codes, feed_last, sizeof(codes));
      drdy = 0;
    }
  }
  spin_unlock_irqrestore(&feed_lock, flags);
  if (!fed) {
    codes[0] = fixp_cos32((int)(n % 360)) >> 9;
    codes[1] = fixp_sin32((int)(n % 360)) >> 9;
    codes[2] = 0x100000;
    codes[3] = (s32)(n & 0x7FFFFF);
  }
  if (READ_ONCE(inject_reset)) {
    WRITE_ONCE(inject_reset, 0);
    device_reset();
  }
  if (data) response = STATUS_WLENGTH24 | drdy | ((mode & MODE_RESET) ? STATUS_RESET : 0);
  put16(out, response);
  put24(out + 3, codes[0]);
  put24(out + 6, codes[1]);
  put24(out + 9, codes[2]);
  put24(out + 12, codes[3]);
  put16(out + 15, crc16_ccitt(out, 15));
  if (data) {
    ++data_frames;
    if (crc_error_every && data_frames % crc_error_every == 0) {
      out[4] ^= 0x01; /* one flipped bit: CRC-16 always detects it */
      ++crc_errors_injected;
    }
  }
}

static void decode_command(const u8* tx, unsigned int len) {
  u16 cmd = tx ? (u16)((tx[0] << 8) | tx[1]) : 0;

  pending_is_status = false;
  if (cmd == 0x0011) { /* RESET */
    device_reset();
    pending_response = RESET_RESPONSE;
  } else if ((cmd & 0xE000) == 0x6000) { /* WREG (of one register: the only form the model keeps) */
    const unsigned int address = (cmd >> 7) & 0x3F;
    const u16 value = len >= 6 ? (u16)((tx[3] << 8) | tx[4]) : 0;

    if (address == REG_GAIN1 && len >= 6) gain1 = value;
    if (address == REG_MODE && len >= 6) mode = value;
    pending_response = 0x4000 | (cmd & 0x1FFF);
  } else { /* NULL and unmodelled commands: STATUS + data */
    pending_is_status = true;
  }
}

static int feed_open_fn(struct inode* inode, struct file* file) {
  unsigned long flags;

  if (atomic_cmpxchg(&feed_open, 0, 1) != 0) return -EBUSY; /* one feeder at a time */
  spin_lock_irqsave(&feed_lock, flags);
  feed_active = true;
  feed_head = 0;
  feed_count = 0;
  memset(feed_last, 0, sizeof(feed_last));
  spin_unlock_irqrestore(&feed_lock, flags);
  return 0;
}

static int feed_release_fn(struct inode* inode, struct file* file) {
  unsigned long flags;

  spin_lock_irqsave(&feed_lock, flags);
  feed_active = false;
  feed_count = 0;
  spin_unlock_irqrestore(&feed_lock, flags);
  atomic_set(&feed_open, 0);
  return 0;
}

/* Each 16-byte record is one conversion, queued; all or nothing per write. */
static ssize_t feed_write_fn(struct file* file, const char __user* buf, size_t len, loff_t* pos) {
  s32 codes[4];
  unsigned long flags;
  size_t done = 0;

  if (len == 0 || len % sizeof(codes) != 0) return -EINVAL;
  if (len / sizeof(codes) > FEED_DEPTH) return -ENOSPC;
  spin_lock_irqsave(&feed_lock, flags);
  if (feed_count + len / sizeof(codes) > FEED_DEPTH) {
    spin_unlock_irqrestore(&feed_lock, flags);
    return -ENOSPC;
  }
  spin_unlock_irqrestore(&feed_lock, flags);
  while (done < len) { /* only this (single) feeder adds: the room checked above stays */
    if (copy_from_user(codes, buf + done, sizeof(codes))) return done ? (ssize_t)done : -EFAULT;
    spin_lock_irqsave(&feed_lock, flags);
    memcpy(feed_fifo[(feed_head + feed_count) % FEED_DEPTH], codes, sizeof(codes));
    ++feed_count;
    ++fed_conversions;
    if (feed_count > fed_max_queued) fed_max_queued = feed_count;
    spin_unlock_irqrestore(&feed_lock, flags);
    done += sizeof(codes);
  }
  return (ssize_t)len;
}

static const struct file_operations feed_fops = {
    .owner = THIS_MODULE,
    .open = feed_open_fn,
    .release = feed_release_fn,
    .write = feed_write_fn,
    .llseek = noop_llseek,
};

static struct miscdevice feed_misc = {
    .minor = MISC_DYNAMIC_MINOR,
    .name = "magvec_adc_feed",
    .fops = &feed_fops,
    .mode = 0600,
};

static int vspi_transfer_one(struct spi_controller* ctlr, struct spi_device* spi,
                             struct spi_transfer* xfer) {
  u8 frame[FRAME_BYTES];
  u8* rx = xfer->rx_buf;
  const u8* tx = xfer->tx_buf;
  unsigned int i;

  if (spi->chip_select == 1) { /* loopback device: MISO wired to MOSI */
    if (rx && tx)
      memcpy(rx, tx, xfer->len);
    else if (rx)
      memset(rx, 0, xfer->len);
    return 0;
  }
  if (xfer->len < 3) { /* too short to carry a command word: ignored, as by the real device */
    if (rx) memset(rx, 0, xfer->len);
    return 0;
  }
  build_frame(frame);
  if (rx)
    for (i = 0; i < xfer->len; ++i)
      rx[i] = i < FRAME_BYTES ? frame[i] : 0;
  decode_command(tx, xfer->len);
  return 0; /* completed synchronously */
}

static int __init vspi_init(void) {
  struct spi_board_info info = {
      .modalias = "dh2228fv", /* in spidev's id table: spidev binds */
      .max_speed_hz = 8000000,
      .bus_num = 0,
      .chip_select = 0,
      .mode = SPI_MODE_1,
  };
  int ret;

  vspi_pdev = platform_device_register_simple("magvec-vspi", -1, NULL, 0);
  if (IS_ERR(vspi_pdev)) return PTR_ERR(vspi_pdev);
  vspi_ctlr = spi_alloc_master(&vspi_pdev->dev, 0);
  if (!vspi_ctlr) {
    ret = -ENOMEM;
    goto err_pdev;
  }
  vspi_ctlr->bus_num = 0;
  vspi_ctlr->num_chipselect = 2;
  vspi_ctlr->mode_bits = SPI_CPOL | SPI_CPHA;
  vspi_ctlr->bits_per_word_mask = SPI_BPW_MASK(8);
  vspi_ctlr->min_speed_hz = 1000;
  vspi_ctlr->max_speed_hz = 25000000;
  vspi_ctlr->transfer_one = vspi_transfer_one;
  ret = spi_register_controller(vspi_ctlr);
  if (ret) {
    spi_controller_put(vspi_ctlr);
    goto err_pdev;
  }
  vspi_dev = spi_new_device(vspi_ctlr, &info);
  if (!vspi_dev) {
    ret = -ENODEV;
    goto err_ctlr;
  }
  info.chip_select = 1; /* a plain loopback device: tests of the transfer path itself */
  info.mode = SPI_MODE_0;
  vspi_loop = spi_new_device(vspi_ctlr, &info);
  if (!vspi_loop) {
    ret = -ENODEV;
    goto err_ctlr;
  }
  ret = misc_register(&feed_misc);
  if (ret) goto err_ctlr;
  pr_info("magvec_vspi: ADS131M04 model on spi0.0, loopback on spi0.1 (crc_error_every=%u)\n",
          crc_error_every);
  return 0;
err_ctlr:
  spi_unregister_controller(vspi_ctlr);
err_pdev:
  platform_device_unregister(vspi_pdev);
  return ret;
}

static void __exit vspi_exit(void) {
  misc_deregister(&feed_misc);
  spi_unregister_device(vspi_loop);
  spi_unregister_device(vspi_dev);
  spi_unregister_controller(vspi_ctlr);
  platform_device_unregister(vspi_pdev);
}

module_init(vspi_init);
module_exit(vspi_exit);
MODULE_DESCRIPTION("magvec: virtual SPI controller with an ADS131M04 model (VM tests)");
MODULE_LICENSE("GPL");
