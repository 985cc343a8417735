/* sm_test_daemon: start and stop the real shapematchd for a test program. Header-only,
 * test code only; one daemon at a time per test program (the globals below).
 *
 * The daemon's stderr goes to a file (a pipe could fill up and block it); its bound port is
 * read from the `msg=listening port=N` line. Stdout/stdin go to /dev/null so ctest's
 * output pipe never waits on the daemon. Include after sm_test.h; needs SM_SERVER_BIN. */
#ifndef SM_TEST_DAEMON_H
#define SM_TEST_DAEMON_H

#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#ifndef SM_SERVER_BIN
#error "SM_SERVER_BIN must name the shapematchd binary"
#endif

static char g_dir[512], g_log[600]; /* test's temp dir; the daemon's log inside it */
static pid_t g_pid = -1;

static inline void sleep_us(long us) {
  struct timespec ts = {us / 1000000, (us % 1000000) * 1000};
  while (nanosleep(&ts, &ts) && errno == EINTR) {
  }
}

static inline void kill_daemon(void) {
  if (g_pid > 0) {
    kill(g_pid, SIGKILL);
    waitpid(g_pid, NULL, 0);
    g_pid = -1;
  }
}

/* Child side: stderr to the log, argv = daemon --port 0 --data-dir DIR/data + the
 * space-separated words of `common` and `extra`. */
static inline void exec_daemon(const char *datadir, const char *common, const char *extra) {
  int fd = open(g_log, O_WRONLY | O_CREAT | O_TRUNC, 0600);
  if (fd < 0) _exit(127);
  dup2(fd, 2);
  close(fd);
  int nul = open("/dev/null", O_RDWR);
  if (nul >= 0) {
    dup2(nul, 0);
    dup2(nul, 1);
    close(nul);
  }
  char *argv[48], words[512];
  int n = 0;
  argv[n++] = (char *)SM_SERVER_BIN;
  argv[n++] = (char *)"--port";
  argv[n++] = (char *)"0";
  argv[n++] = (char *)"--data-dir";
  argv[n++] = (char *)datadir;
  snprintf(words, sizeof words, "%s %s", common ? common : "", extra ? extra : "");
  for (char *t = strtok(words, " "); t && n < 46; t = strtok(NULL, " ")) argv[n++] = t;
  argv[n] = NULL;
  execv(argv[0], argv);
  _exit(127);
}

/* Flips one byte in the middle of a file, as a disk or a stray writer would: the store
 * tests damage shape and basis files with it. */
static inline void damage_file(const char *path) {
  FILE *f = fopen(path, "r+b");
  REQUIRE(f);
  fseek(f, 0, SEEK_END);
  long sz = ftell(f);
  fseek(f, sz / 2, SEEK_SET);
  int ch = fgetc(f);
  fseek(f, sz / 2, SEEK_SET);
  fputc(ch ^ 0x5a, f);
  fclose(f);
}

/* Starts the daemon on g_dir/data; returns its port, or -1 (it exited or never listened
 * within 60 s). */
static inline int start_daemon_with(const char *common, const char *extra) {
  snprintf(g_log, sizeof g_log, "%s/daemon.log", g_dir);
  char datadir[600];
  snprintf(datadir, sizeof datadir, "%s/data", g_dir);
  unlink(g_log); /* else the previous run's `listening` line could be read */
  pid_t pid = fork();
  REQUIRE(pid >= 0);
  if (pid == 0) exec_daemon(datadir, common, extra);
  g_pid = pid;
  for (int tries = 0; tries < 1200; tries++) {
    FILE *f = fopen(g_log, "r");
    char line[1024];
    int port = -1;
    while (f && fgets(line, sizeof line, f)) {
      char *p = strstr(line, "msg=listening port=");
      if (p) port = atoi(p + strlen("msg=listening port="));
    }
    if (f) fclose(f);
    if (port > 0) return port;
    int st;
    if (waitpid(pid, &st, WNOHANG) == pid) {
      g_pid = -1;
      fprintf(stderr, "daemon exited early (status %d)\n", st);
      return -1;
    }
    sleep_us(50000);
  }
  return -1;
}

/* SIGTERM; returns the exit status (128 + signal if killed), or -1 after 60 s (then
 * SIGKILL). */
static inline int stop_daemon(void) {
  kill(g_pid, SIGTERM);
  int st = 0;
  for (int i = 0; i < 1200; i++) {
    if (waitpid(g_pid, &st, WNOHANG) == g_pid) {
      g_pid = -1;
      return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
    }
    sleep_us(50000);
  }
  kill_daemon();
  return -1;
}

#endif
