#include "bench/support/pytorch_peer.hpp"

#include <fcntl.h>
#include <fmt/format.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <cstring>
#include <sstream>

#include "bench/support/model_options.hpp"
#include "core/error.hpp"
#include "core/parallel.hpp"

namespace pillarseg::bench {

std::map<std::string, std::string> parse_fields(const std::string& line) {
  std::map<std::string, std::string> fields;
  std::istringstream in(line.substr(line.find(' ') + 1));
  std::string token;
  while (in >> token) {
    const size_t eq = token.find('=');
    if (eq != std::string::npos) fields[token.substr(0, eq)] = token.substr(eq + 1);
  }
  return fields;
}


PeerProcess::PeerProcess(const std::vector<std::string>& arguments) {
  std::vector<std::string> args{options().peer_python, options().peer_script.string(),
                                "--threads", std::to_string(num_threads()), "--serve"};
  args.insert(args.end(), arguments.begin(), arguments.end());
  std::vector<char*> argv;
  for (std::string& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  int to_child[2], from_child[2];
  PS_CHECK(pipe2(to_child, O_CLOEXEC) == 0 && pipe2(from_child, O_CLOEXEC) == 0,
           "cannot create pipes for the PyTorch peer: {}", std::strerror(errno));
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_adddup2(&actions, to_child[0], STDIN_FILENO);
  posix_spawn_file_actions_adddup2(&actions, from_child[1], STDOUT_FILENO);
  posix_spawn_file_actions_adddup2(&actions, from_child[1], STDERR_FILENO);
  const int error = posix_spawn(&pid_, argv[0], &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  close(to_child[0]);
  close(from_child[1]);
  if (error != 0) {
    close(to_child[1]);
    close(from_child[0]);
    pid_ = -1;
    failure_ = fmt::format("skipped: cannot run {}: {}", args[0], std::strerror(error));
    return;
  }
  to_peer_ = fdopen(to_child[1], "w");
  from_peer_ = fdopen(from_child[0], "r");
  std::string ready;
  if (!read_until("PEER_READY", ready)) finish();  // it stopped: skipped (no torch) or failed
}

std::optional<double> PeerProcess::step(const std::string& command, StepTimes& times) {
  if (!ok() || pid_ < 0) return std::nullopt;
  std::string answer;
  const bool sent =
      std::fputs((command + "\n").c_str(), to_peer_) >= 0 && std::fflush(to_peer_) == 0;
  if (!sent || !read_until("PEER_STEP ", answer)) {
    finish();
    if (ok()) failure_ = fmt::format("the PyTorch peer stopped answering '{}'", command);
    return std::nullopt;
  }
  const auto fields = parse_fields(answer);
  times.add(std::stod(fields.at("wall_ms")) * 1e-3, std::stod(fields.at("cpu_ms")) * 1e-3);
  return times.wall.back();
}

void PeerProcess::finish() {
  if (pid_ < 0) return;
  std::fclose(to_peer_);
  std::string unused;
  read_until("", unused, /*to_end=*/true);
  std::fclose(from_peer_);
  int status = 0;
  waitpid(pid_, &status, 0);
  pid_ = -1;
  const int exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  for (const std::string& line : lines_) {
    if (line.rfind("PEER ", 0) == 0) summary_ = line;
  }
  if (summary_.rfind("PEER skipped", 0) == 0) {
    failure_ = summary_.substr(5);
  } else if (exit_code != 0 || summary_.empty()) {
    std::string output;
    for (const std::string& line : lines_) output += "\n    " + line;
    failure_ = fmt::format("the PyTorch peer failed (exit {}):{}", exit_code, output);
  }
}

bool PeerProcess::read_until(const std::string& prefix, std::string& line, bool to_end) {
  std::array<char, 4096> buffer{};
  while (std::fgets(buffer.data(), static_cast<int>(buffer.size()), from_peer_) != nullptr) {
    line = buffer.data();
    if (!line.empty() && line.back() == '\n') line.pop_back();
    if (!to_end && line.rfind(prefix, 0) == 0) return true;
    lines_.push_back(line);
  }
  return false;
}

}  // namespace pillarseg::bench
