/* trimeter-fw-sim: the firmware core as a Linux process (see README.md).
 *
 * One thread, one poll() loop. Simulated time runs --time-scale times wall time; each loop turn
 * advances it in slices of at most SLICE_US, and within a slice every due step-timer tick calls the
 * core's ISR at its own simulated instant before app_poll() runs, as on the MCU. */
#include <errno.h>
#include <fcntl.h>
#include <getopt.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "app.h"
#include "c12880_chip.h"
#include "plant.h"

#define SLICE_US 1000u           /* the main loop runs at least once per simulated ms */
#define MAX_CATCH_UP_US 200000u  /* per loop turn; beyond it simulated time slips behind wall × K */
#define MAX_CLIENTS 8
#define LINE_MAX_BYTES 4096
#define STORAGE_BYTES (2u * HAL_CONFIG_REGION_SIZE + 2u * HAL_MAP_REGION_SIZE)

typedef struct client {
    int fd;
    char line[LINE_MAX_BYTES + 1];
    size_t len;
    bool discarding; /* the current line overflowed: drop it up to the newline */
} client_t;

static struct sim {
    /* clock */
    double time_scale;
    struct timespec wall_start;
    uint64_t now_us;     /* simulated, what the HAL reports */
    uint64_t slipped_us; /* simulated time given up because the host couldn't keep up */
    /* step timer */
    bool timer_running;
    uint64_t timer_due_us;
    /* I/O */
    int pty_master, pty_slave_keepalive;
    bool pty_readable;   /* poll() saw input; cleared once a read drains it (saves a syscall per slice) */
    int listen_fd;
    client_t clients[MAX_CLIENTS];
    /* storage */
    int storage_fd;
    _Alignas(8) uint8_t storage[STORAGE_BYTES]; /* the inverse core reads a map slot in place */
    plant_t plant;
    chip_t chip; /* the micro-spectrometer, physical: survives a reset */
    uint8_t address_override;
} sim;

static volatile sig_atomic_t stop_requested;

static void on_signal(int sig)
{
    (void)sig;
    stop_requested = 1;
}

static void die(const char *what)
{
    fprintf(stderr, "trimeter-fw-sim: %s\n", what);
    exit(2);
}

/* ---------------------------------------------------------------- HAL */

static size_t h_uart_read(void *ctx, uint8_t *buf, size_t max)
{
    (void)ctx;
    if (!sim.pty_readable) return 0;
    ssize_t n = read(sim.pty_master, buf, max);
    if (n <= 0 || (size_t)n < max) sim.pty_readable = false;
    return n > 0 ? (size_t)n : 0;
}

static size_t h_uart_write(void *ctx, const uint8_t *buf, size_t len)
{
    (void)ctx;
    size_t done = 0;
    while (done < len) {
        ssize_t n = write(sim.pty_master, buf + done, len - done);
        if (n > 0) {
            done += (size_t)n;
        } else if (n < 0 && errno == EAGAIN) {
            struct pollfd p = {.fd = sim.pty_master, .events = POLLOUT};
            if (poll(&p, 1, 100) <= 0) break; /* nobody reads the line: drop the rest */
        } else {
            break;
        }
    }
    return done;
}

static uint32_t h_now_us(void *ctx)
{
    (void)ctx;
    return (uint32_t)sim.now_us;
}

static void h_enable(void *ctx, bool on) { (void)ctx; sim.plant.stepper_enabled = on; }
static void h_dir(void *ctx, bool positive) { (void)ctx; sim.plant.dir_positive = positive; }
static void h_step(void *ctx) { (void)ctx; plant_step(&sim.plant); }
static bool h_endstop(void *ctx) { (void)ctx; return plant_endstop(&sim.plant); }
static bool h_stalled(void *ctx) { (void)ctx; return sim.plant.driver_stalled; }

static void h_timer_start(void *ctx, uint32_t first_us)
{
    (void)ctx;
    sim.timer_running = true;
    sim.timer_due_us = sim.now_us + first_us;
}

static void h_timer_stop(void *ctx) { (void)ctx; sim.timer_running = false; }
static void h_servo(void *ctx, enum hal_shutter s, uint16_t us) { (void)ctx; sim.plant.servo_pulse_us[s] = us; }
static void h_led(void *ctx, enum hal_led l, uint16_t pm) { (void)ctx; sim.plant.led_permille[l] = pm; }
static void h_status(void *ctx, bool on) { (void)ctx; sim.plant.status_led = on; }
static bool h_button(void *ctx) { (void)ctx; return plant_button(&sim.plant, sim.now_us); }
static void h_kick(void *ctx) { (void)ctx; }
static uint16_t h_lamp(void *ctx, enum hal_led l) { (void)ctx; return plant_lamp_monitor(&sim.plant, l); }
static uint32_t h_spectro_clock(void *ctx) { (void)ctx; return chip_clock_hz(&sim.chip); }
static int h_spectro_start(void *ctx, const hal_spectro_timing_t *t)
{
    (void)ctx;
    return chip_start(&sim.chip, &sim.plant, t, sim.now_us);
}
static enum hal_spectro_result h_spectro_read(void *ctx, uint16_t *video, size_t pixels)
{
    (void)ctx;
    return chip_read(&sim.chip, video, pixels, sim.now_us);
}

static const uint32_t region_offset[HAL_REGION_COUNT] = {
    0, HAL_CONFIG_REGION_SIZE, 2 * HAL_CONFIG_REGION_SIZE, 2 * HAL_CONFIG_REGION_SIZE + HAL_MAP_REGION_SIZE};

static uint8_t *region(enum hal_region r, uint32_t offset, size_t len, uint32_t *file_offset)
{
    if ((unsigned)r >= HAL_REGION_COUNT) return NULL;
    uint32_t size = r <= HAL_REGION_CONFIG_B ? HAL_CONFIG_REGION_SIZE : HAL_MAP_REGION_SIZE;
    if (offset > size || len > size - offset) return NULL;
    *file_offset = region_offset[r] + offset;
    return sim.storage + *file_offset;
}

static int persist(uint32_t file_offset, size_t len)
{
    ssize_t n = pwrite(sim.storage_fd, sim.storage + file_offset, len, file_offset);
    return n == (ssize_t)len ? 0 : -1;
}

static int h_read(void *ctx, enum hal_region r, uint32_t offset, void *buf, size_t len)
{
    (void)ctx;
    uint32_t fo;
    uint8_t *p = region(r, offset, len, &fo);
    if (!p) return -1;
    memcpy(buf, p, len);
    return 0;
}

static int h_write(void *ctx, enum hal_region r, uint32_t offset, const void *buf, size_t len)
{
    (void)ctx;
    uint32_t fo;
    uint8_t *p = region(r, offset, len, &fo);
    const uint8_t *src = buf;
    if (!p) return -1;
    for (size_t i = 0; i < len; i++) p[i] &= src[i]; /* NOR flash: programming only clears bits */
    return persist(fo, len);
}

static int h_erase(void *ctx, enum hal_region r)
{
    (void)ctx;
    uint32_t fo;
    uint32_t size = r <= HAL_REGION_CONFIG_B ? HAL_CONFIG_REGION_SIZE : HAL_MAP_REGION_SIZE;
    uint8_t *p = region(r, 0, size, &fo);
    if (!p) return -1;
    memset(p, 0xFF, size);
    return persist(fo, size);
}

static const uint8_t *h_map_bytes(void *ctx, enum hal_region r)
{
    (void)ctx;
    uint32_t fo;
    return r == HAL_REGION_MAP_A || r == HAL_REGION_MAP_B ? region(r, 0, HAL_MAP_REGION_SIZE, &fo) : NULL;
}

static const hal_t sim_hal = {
    .ctx = NULL,
    .uart_read = h_uart_read,
    .uart_write = h_uart_write,
    .now_us = h_now_us,
    .stepper_enable = h_enable,
    .stepper_dir = h_dir,
    .stepper_step = h_step,
    .endstop_active = h_endstop,
    .stepper_stalled = h_stalled,
    .step_timer_start = h_timer_start,
    .step_timer_stop = h_timer_stop,
    .servo_pulse_us = h_servo,
    .led_level = h_led,
    .status_led = h_status,
    .button_pressed = h_button,
    .lamp_monitor = h_lamp,
    .spectro_clock_hz = h_spectro_clock,
    .spectro_start = h_spectro_start,
    .spectro_read = h_spectro_read,
    .storage_read = h_read,
    .storage_write = h_write,
    .storage_erase = h_erase,
    .storage_map_bytes = h_map_bytes,
    .watchdog_kick = h_kick,
};

/* ---------------------------------------------------------------- set-up */

static void open_storage(const char *path)
{
    sim.storage_fd = open(path, O_RDWR | O_CREAT | O_CLOEXEC, 0644);
    if (sim.storage_fd < 0) die("cannot open --storage file");
    struct stat st;
    if (fstat(sim.storage_fd, &st) != 0) die("cannot stat --storage file");
    if (st.st_size == 0) {
        memset(sim.storage, 0xFF, sizeof sim.storage); /* a fresh, erased flash */
        if (persist(0, sizeof sim.storage) != 0) die("cannot write --storage file");
    } else if (st.st_size != (off_t)sizeof sim.storage) {
        /* never overwrite something that isn't ours */
        fprintf(stderr, "trimeter-fw-sim: --storage %s is %lld bytes, expected %u (not a sim storage image)\n",
                path, (long long)st.st_size, (unsigned)sizeof sim.storage);
        exit(2);
    } else if (pread(sim.storage_fd, sim.storage, sizeof sim.storage, 0) != (ssize_t)sizeof sim.storage) {
        die("cannot read --storage file");
    }
}

static void open_pty(const char *link_path)
{
    sim.pty_master = posix_openpt(O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
    if (sim.pty_master < 0 || grantpt(sim.pty_master) != 0 || unlockpt(sim.pty_master) != 0) die("cannot open a pty");
    const char *slave = ptsname(sim.pty_master);
    if (!slave) die("ptsname failed");
    /* Keep the slave open ourselves: without it the master sees HUP whenever no client is
     * connected and poll() would spin. Raw mode: Modbus is binary. */
    sim.pty_slave_keepalive = open(slave, O_RDWR | O_NOCTTY | O_CLOEXEC);
    if (sim.pty_slave_keepalive < 0) die("cannot open the pty slave");
    struct termios t;
    if (tcgetattr(sim.pty_slave_keepalive, &t) == 0) {
        cfmakeraw(&t);
        tcsetattr(sim.pty_slave_keepalive, TCSANOW, &t);
    }
    unlink(link_path);
    if (symlink(slave, link_path) != 0) die("cannot create the --modbus-link symlink");
}

static void open_socket(const char *path)
{
    struct sockaddr_un addr = {.sun_family = AF_UNIX};
    if (strlen(path) >= sizeof addr.sun_path) die("--plant-link path too long for a unix socket");
    strcpy(addr.sun_path, path);
    sim.listen_fd = socket(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (sim.listen_fd < 0) die("cannot create the plant socket");
    unlink(path);
    if (bind(sim.listen_fd, (struct sockaddr *)&addr, sizeof addr) != 0 || listen(sim.listen_fd, MAX_CLIENTS) != 0)
        die("cannot listen on --plant-link");
    for (int i = 0; i < MAX_CLIENTS; i++) sim.clients[i].fd = -1;
}

/* ---------------------------------------------------------------- time */

static uint64_t wall_target_us(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    double wall_s = (double)(t.tv_sec - sim.wall_start.tv_sec) + (t.tv_nsec - sim.wall_start.tv_nsec) * 1e-9;
    uint64_t target = (uint64_t)(wall_s * sim.time_scale * 1e6) - sim.slipped_us;
    /* A slow host (or a huge --time-scale) must not make the loop chase an ever-growing backlog
     * and stop serving its sockets: let simulated time slip instead. */
    if (target > sim.now_us + MAX_CATCH_UP_US) {
        sim.slipped_us += target - (sim.now_us + MAX_CATCH_UP_US);
        target = sim.now_us + MAX_CATCH_UP_US;
    }
    return target;
}

/* Advances simulated time to `target`, slice by slice, as the MCU would live through it. */
static void advance_to(uint64_t target)
{
    while (sim.now_us < target) {
        uint64_t slice_end = sim.now_us + SLICE_US < target ? sim.now_us + SLICE_US : target;
        while (sim.timer_running && sim.timer_due_us <= slice_end) {
            sim.now_us = sim.timer_due_us;
            plant_update(&sim.plant, sim.now_us);
            uint32_t next = app_step_isr();
            if (!sim.timer_running) continue; /* stopped from inside */
            if (next == 0) sim.timer_running = false;
            else if (sim.timer_due_us == sim.now_us) sim.timer_due_us = sim.now_us + next;
        }
        sim.now_us = slice_end;
        plant_update(&sim.plant, sim.now_us);
        app_poll();
    }
}

/* ---------------------------------------------------------------- plant socket */

static void reboot_firmware(void)
{
    app_init(&sim_hal);
    if (sim.address_override) app_override_modbus_address(sim.address_override);
}

static void send_all(int fd, const char *buf, size_t len)
{
    while (len > 0) {
        ssize_t n = send(fd, buf, len, MSG_NOSIGNAL);
        if (n > 0) {
            buf += n;
            len -= (size_t)n;
        } else if (n < 0 && errno == EAGAIN) {
            struct pollfd p = {.fd = fd, .events = POLLOUT};
            if (poll(&p, 1, 1000) <= 0) return;
        } else {
            return;
        }
    }
}

static void handle_line(client_t *c)
{
    static char reply[4096];
    bool reset = false;
    c->line[c->len] = 0;
    size_t n;
    if (!chip_handle_request(&sim.chip, c->line, reply, sizeof reply, &n))
        n = plant_handle_request(&sim.plant, c->line, sim.now_us, reply, sizeof reply, &reset);
    if (reset) reboot_firmware();
    send_all(c->fd, reply, n);
}

static void close_client(client_t *c)
{
    close(c->fd);
    c->fd = -1;
    c->len = 0;
    c->discarding = false;
}

static void serve_client(client_t *c)
{
    char buf[1024];
    ssize_t n = recv(c->fd, buf, sizeof buf, 0);
    if (n == 0 || (n < 0 && errno != EAGAIN && errno != EINTR)) {
        close_client(c);
        return;
    }
    for (ssize_t i = 0; i < n; i++) {
        char ch = buf[i];
        if (ch == '\n') {
            if (c->discarding) {
                static const char msg[] = "{\"ok\":false,\"error\":\"request line longer than 4096 bytes\"}\n";
                send_all(c->fd, msg, sizeof msg - 1);
            } else if (c->len > 0) {
                handle_line(c);
            }
            c->len = 0;
            c->discarding = false;
        } else if (!c->discarding) {
            if (c->len == LINE_MAX_BYTES) c->discarding = true;
            else c->line[c->len++] = ch;
        }
    }
}

static void accept_clients(void)
{
    for (;;) {
        int fd = accept4(sim.listen_fd, NULL, NULL, SOCK_NONBLOCK | SOCK_CLOEXEC);
        if (fd < 0) return;
        int slot = -1;
        for (int i = 0; i < MAX_CLIENTS; i++)
            if (sim.clients[i].fd < 0) slot = i;
        if (slot < 0) {
            static const char msg[] = "{\"ok\":false,\"error\":\"too many plant clients\"}\n";
            send_all(fd, msg, sizeof msg - 1);
            close(fd);
            continue;
        }
        sim.clients[slot] = (client_t){.fd = fd};
    }
}

/* ---------------------------------------------------------------- main */

static void usage(void)
{
    fprintf(stderr, "usage: trimeter-fw-sim --storage FILE --modbus-link PATH --plant-link PATH "
                    "[--address N] [--time-scale K] [--steps-per-mm S] [--slider-mm X]\n");
    exit(2);
}

static double parse_number(const char *s, const char *name, double lo, double hi)
{
    char *end;
    double v = strtod(s, &end);
    if (end == s || *end || !(v >= lo && v <= hi)) {
        fprintf(stderr, "trimeter-fw-sim: %s must be a number in [%g, %g], got '%s'\n", name, lo, hi, s);
        exit(2);
    }
    return v;
}

int main(int argc, char **argv)
{
    const char *storage = NULL, *modbus_link = NULL, *plant_link = NULL;
    double steps_per_mm = REG_HR_STEPS_PER_MM_DEFAULT, slider_mm = 50.0;
    sim.time_scale = 1.0;
    static const struct option options[] = {
        {"storage", required_argument, 0, 's'},    {"modbus-link", required_argument, 0, 'm'},
        {"plant-link", required_argument, 0, 'p'}, {"address", required_argument, 0, 'a'},
        {"time-scale", required_argument, 0, 't'}, {"steps-per-mm", required_argument, 0, 'k'},
        {"slider-mm", required_argument, 0, 'x'},  {"help", no_argument, 0, 'h'},
        {0, 0, 0, 0}};
    int opt;
    while ((opt = getopt_long(argc, argv, "", options, NULL)) != -1) {
        switch (opt) {
        case 's': storage = optarg; break;
        case 'm': modbus_link = optarg; break;
        case 'p': plant_link = optarg; break;
        case 'a': sim.address_override = (uint8_t)parse_number(optarg, "--address", 1, 247); break;
        case 't': sim.time_scale = parse_number(optarg, "--time-scale", 1e-3, 1e4); break;
        case 'k': steps_per_mm = parse_number(optarg, "--steps-per-mm", 1, 10000); break;
        case 'x': slider_mm = parse_number(optarg, "--slider-mm", 0, REG_HR_SLOT_OPEN_MM_MAX); break;
        default: usage();
        }
    }
    if (!storage || !modbus_link || !plant_link || optind != argc) usage();

    struct sigaction sa = {.sa_handler = on_signal};
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    open_storage(storage);
    plant_init(&sim.plant, steps_per_mm, slider_mm);
    chip_init(&sim.chip);
    clock_gettime(CLOCK_MONOTONIC, &sim.wall_start);
    reboot_firmware();
    open_pty(modbus_link);
    open_socket(plant_link);
    printf("ready\n");
    fflush(stdout);

    while (!stop_requested) {
        struct pollfd fds[2 + MAX_CLIENTS];
        int nfds = 0;
        fds[nfds++] = (struct pollfd){.fd = sim.pty_master, .events = POLLIN};
        fds[nfds++] = (struct pollfd){.fd = sim.listen_fd, .events = POLLIN};
        for (int i = 0; i < MAX_CLIENTS; i++)
            if (sim.clients[i].fd >= 0) fds[nfds++] = (struct pollfd){.fd = sim.clients[i].fd, .events = POLLIN};
        /* Modbus bytes are read by app_poll (mb_poll) in the next slice; only wake up for them here. */
        if (poll(fds, (nfds_t)nfds, 1) < 0 && errno != EINTR) break;
        if (fds[0].revents & POLLIN) sim.pty_readable = true;
        advance_to(wall_target_us());
        if (fds[1].revents & POLLIN) accept_clients();
        for (int i = 0; i < MAX_CLIENTS; i++) {
            client_t *c = &sim.clients[i];
            if (c->fd < 0) continue;
            for (int k = 2; k < nfds; k++)
                if (fds[k].fd == c->fd && (fds[k].revents & (POLLIN | POLLHUP | POLLERR))) serve_client(c);
        }
    }

    unlink(modbus_link);
    unlink(plant_link);
    for (int i = 0; i < MAX_CLIENTS; i++)
        if (sim.clients[i].fd >= 0) close(sim.clients[i].fd);
    close(sim.listen_fd);
    close(sim.pty_master);
    close(sim.storage_fd);
    return 0;
}
