// The simulation steps of a policy step of B freeway roads, fused into one loop per road (CPU).
//
// The same computation as RoadPhysics.substep (physics.py) and highway-env's Road.act +
// Road.step, vehicle by vehicle in highway-env's order: every driving vehicle acts (follow_road,
// the abort of a lane change or MOBIL, the lateral controller, IDM or the emergency stop) after
// the vehicles before it, so the abort rule reads their targets as highway-env does; then every
// vehicle moves; then the candidate pairs (a vehicle with its leader in its lane and its leaders
// and followers in the lanes beside it) are tested for collisions in highway-env's pair order.
// Arithmetic in double, as highway-env's; the state is stored in the simulator's dtype.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

namespace {

constexpr double kPi = 3.14159265358979323846;

struct Constants {
  double comfort_acc_max, comfort_acc_min, distance_wanted, time_wanted, delta_default;
  double acc_max, acc_min, kp_lateral, kp_heading, max_steering, length, lane_width;
  double vehicle_length, lane_change_delay, min_gain, max_braking, speed_limit, dt, sqrt_ab;
  int64_t n_tables, ramp_table;
  bool merge;
};

struct Finish {  // the scenario's observation and reward settings
  double comfort_threshold, velocity_weight, collision_reward, perception, merge_start, merge_end;
  double lane_change_comfort;
  bool team_reward, merge;
};

struct Lanes {
  const double *sx, *sy, *ux, *uy, *heading, *length;
  const bool* forbidden;
  const int64_t *table, *segment, *side, *next_lane, *number;
  int64_t count;
};

double not_zero(double v) {
  const double eps = 1e-2;
  if (std::abs(v) > eps) return v;
  return v >= 0 ? eps : -eps;
}

double py_mod(double a, double b) {  // Python's float modulo (sign of the divisor)
  double r = std::fmod(a, b);
  if (r != 0 && ((r < 0) != (b < 0))) r += b;
  return r;
}

double wrap_to_pi(double x) { return x == 0 ? 0.0 : py_mod(x + kPi, 2 * kPi) - kPi; }

double clip(double v, double lo, double hi) { return std::min(std::max(v, lo), hi); }

template <typename T>
struct Road {
  T *x, *y, *heading, *speed, *target_speed, *delta, *acc, *steer, *impact_x, *impact_y;
  double* timer;
  int64_t *lane, *target, *decision;
  bool *crashed, *present, *has_impact, *cav;
  int64_t n;
};

template <typename T>
class Stepper {
 public:
  Stepper(const Constants& c, const Lanes& l, const bool* obstacle, const double* body_length,
          const double* body_width, int64_t n)
      : c_(c), l_(l), obstacle_(obstacle), blen_(body_length), bwid_(body_width), n_(n),
        order_(n), rank_(n), upper_(n), after_((c.n_tables) * (n + 1)),
        before_((c.n_tables) * (n + 1)), front_(3 * n), rear_(3 * n), cos_(n), sin_(n),
        diag_(n), comfort_(n), sorted_table_(n) {
    for (int64_t i = 0; i < n; ++i)
      diag_[i] = std::sqrt(body_length[i] * body_length[i] + body_width[i] * body_width[i]);
  }

  void local(double x, double y, int64_t lane, double* s, double* r) const {
    double dx = x - l_.sx[lane], dy = y - l_.sy[lane];
    *s = dx * l_.ux[lane] + dy * l_.uy[lane];
    *r = dx * (-l_.uy[lane]) + dy * l_.ux[lane];
  }

  // leaders / followers in the tables own - 1, own, own + 1 (-1: none); highway-env's search
  void neighbours(const Road<T>& r, bool fresh) {
    // bodies on the road by x, ties by index; within a policy step the bodies on the road do
    // not change and rarely overtake, so an insertion sort of the last order is linear
    if (fresh) {
      m_ = 0;
      for (int64_t i = 0; i < n_; ++i)
        if (r.present[i]) order_[m_++] = i;
    }
    const int64_t m = m_;
    for (int64_t p = 1; p < m; ++p) {
      const int64_t body = order_[p];
      const T xb = r.x[body];
      int64_t q = p - 1;
      while (q >= 0 && (r.x[order_[q]] > xb || (r.x[order_[q]] == xb && order_[q] > body))) {
        order_[q + 1] = order_[q];
        --q;
      }
      order_[q + 1] = body;
    }
    for (int64_t p = 0; p < m; ++p) rank_[order_[p]] = p;
    for (int64_t p = m - 1; p >= 0; --p)
      upper_[p] = (p == m - 1 || r.x[order_[p + 1]] != r.x[order_[p]]) ? p : upper_[p + 1];
    const int64_t w = n_ + 1;
    for (int64_t p = 0; p < m; ++p) sorted_table_[p] = l_.table[r.lane[order_[p]]];
    for (int64_t t = 0; t < c_.n_tables; ++t) {
      int64_t* after = &after_[t * w];
      int64_t* before = &before_[t * w];  // before[p + 1]: last position <= p in table t
      after[m] = m;
      for (int64_t p = m - 1; p >= 0; --p) after[p] = sorted_table_[p] == t ? p : after[p + 1];
      before[0] = -1;
      for (int64_t p = 0; p < m; ++p) before[p + 1] = sorted_table_[p] == t ? p : before[p];
    }
    for (int64_t i = 0; i < n_; ++i) {
      for (int k = 0; k < 3; ++k) front_[3 * i + k] = rear_[3 * i + k] = -1;
      if (!r.present[i]) continue;
      const int64_t own = l_.table[r.lane[i]], pos = rank_[i], top = upper_[pos];
      for (int k = 0; k < 3; ++k) {
        const int64_t q = own + k - 1;
        if (q < 0 || q >= c_.n_tables) continue;
        const int64_t fp = after_[q * w + top + 1];
        int64_t rp = before_[q * w + top + 1];
        if (rp == pos) rp = before_[q * w + pos];
        front_[3 * i + k] = fp < m ? order_[fp] : -1;
        rear_[3 * i + k] = rp >= 0 ? order_[rp] : -1;
      }
    }
  }

  // cos / sin of every body's heading, once per simulation step (exact 1 / 0 at heading 0)
  void cache_headings(const Road<T>& r) {
    for (int64_t i = 0; i < n_; ++i) {
      const double h = r.heading[i];
      cos_[i] = h == 0 ? 1.0 : std::cos(h);
      sin_[i] = h == 0 ? 0.0 : std::sin(h);
    }
  }

  double desired_gap(const Road<T>& r, int64_t ego, int64_t other) const {
    const double v = r.speed[ego], c = cos_[ego], s = sin_[ego];
    const double vo = r.speed[other];
    const double dv = (v * c - vo * cos_[other]) * c + (v * s - vo * sin_[other]) * s;
    return c_.distance_wanted + v * c_.time_wanted + v * dv / (2 * c_.sqrt_ab);
  }

  // IDMVehicle.acceleration(ego, front) with the deciding vehicle's exponent delta
  double idm(const Road<T>& r, int64_t ego, int64_t front, double delta) const {
    if (ego < 0 || obstacle_[ego]) return 0.0;
    const double target = clip(r.target_speed[ego], 0.0, c_.speed_limit);
    const double ratio = std::max(static_cast<double>(r.speed[ego]), 0.0) /
                         std::abs(not_zero(target));
    double acc = c_.comfort_acc_max * (1 - std::pow(ratio, delta));
    if (front >= 0) {
      const double d = static_cast<double>(r.x[front]) - r.x[ego];
      const double gap = desired_gap(r, ego, front) / not_zero(d);
      acc -= c_.comfort_acc_max * (gap * gap);
    }
    return acc;
  }

  double steering(const Road<T>& r, int64_t i, int64_t lane) const {
    double s, lat;
    local(r.x[i], r.y[i], lane, &s, &lat);
    if (lat == 0 && r.heading[i] == l_.heading[lane]) return 0.0;  // every term is exactly 0
    const double speed = not_zero(r.speed[i]);
    const double heading_command = std::asin(clip(-c_.kp_lateral * lat / speed, -1, 1));
    const double heading_ref = l_.heading[lane] + clip(heading_command, -kPi / 4, kPi / 4);
    const double rate = c_.kp_heading * wrap_to_pi(heading_ref - r.heading[i]);
    const double slip = std::asin(clip(c_.length / 2 / speed * rate, -1, 1));
    return clip(std::atan(2 * std::tan(slip)), -c_.max_steering, c_.max_steering);
  }

  void act(Road<T>& r) {
    cache_headings(r);
    for (int64_t i = 0; i < n_; ++i) {
      if (obstacle_[i] || !r.present[i] || r.crashed[i]) continue;
      const bool stop = r.cav[i] && r.decision[i] == 3;
      const int64_t lane = r.lane[i];
      int64_t target = r.target[i];
      double s, lat;
      local(r.x[i], r.y[i], target, &s, &lat);
      if (s > l_.length[target] - c_.vehicle_length / 2) target = l_.next_lane[target];
      const bool changer = c_.merge ? (!r.cav[i] || l_.table[lane] == c_.ramp_table) : !r.cav[i];
      const double delta = r.delta[i];
      const double self_a = idm(r, i, front_[3 * i + 1], delta);
      if (!stop && changer) {
        if (lane != target) {
          if (l_.segment[lane] == l_.segment[target]) {
            for (int64_t v = 0; v < n_; ++v) {
              if (v == i || obstacle_[v] || !r.present[v]) continue;
              if (r.lane[v] == target || r.target[v] != target) continue;
              const double d = static_cast<double>(r.x[v]) - r.x[i];
              if (0 < d && d < desired_gap(r, i, v)) {
                target = lane;
                break;
              }
            }
          }
        } else if (r.timer[i] > c_.lane_change_delay) {
          r.timer[i] = 0;
          for (int k = 0; k < 2; ++k) {
            const int64_t side = l_.side[2 * lane + k];
            if (side < 0 || l_.forbidden[side]) continue;
            double ss, rr;
            local(r.x[i], r.y[i], side, &ss, &rr);
            if (!(std::abs(rr) <= 2 * c_.lane_width && 0 <= ss &&
                  ss < l_.length[side] + c_.vehicle_length))
              continue;
            if (std::abs(static_cast<double>(r.speed[i])) < 1) continue;
            const int q = k == 0 ? 0 : 2;
            const int64_t new_front = front_[3 * i + q], new_rear = rear_[3 * i + q];
            if (idm(r, new_rear, i, delta) < -c_.max_braking) continue;
            if (idm(r, i, new_front, delta) - self_a < c_.min_gain) continue;
            target = side;
          }
        }
      }
      r.target[i] = target;
      double acc = self_a;
      if (lane != target) {
        const int64_t column = clip(l_.table[target] - l_.table[lane] + 1, 0, 2);
        acc = std::min(acc, idm(r, i, front_[3 * i + column], delta));
      }
      acc = clip(acc, -c_.acc_max, c_.acc_max);
      if (stop) acc = r.speed[i] > 0 ? c_.acc_min : 0.0;
      r.acc[i] = static_cast<T>(acc);
      r.steer[i] = static_cast<T>(steering(r, i, target));
    }
  }

  // the first lane of least |lateral| + distance beyond its ends + |heading difference|,
  // starting from the current lane (a lane whose |lateral| alone exceeds the best cannot win)
  int64_t closest_lane(double x, double y, double h, int64_t current) const {
    auto distance = [&](int64_t k, double s, double lat) {
      return std::abs(lat) + std::max(s - l_.length[k], 0.0) + std::max(-s, 0.0) +
             std::abs(wrap_to_pi(h - l_.heading[k]));
    };
    double s, lat;
    local(x, y, current, &s, &lat);
    int64_t best = current;
    double best_d = distance(current, s, lat);
    for (int64_t k = 0; k < l_.count; ++k) {
      if (k == current) continue;
      local(x, y, k, &s, &lat);
      if (std::abs(lat) > best_d) continue;
      const double d = distance(k, s, lat);
      if (d < best_d || (d == best_d && k < best)) best_d = d, best = k;
    }
    return best;
  }

  void move(Road<T>& r) {
    const double dt = c_.dt;
    for (int64_t i = 0; i < n_; ++i) {
      if (obstacle_[i] || !r.present[i]) continue;
      double speed = r.speed[i], acc = r.acc[i], steer = r.steer[i];
      const bool crashed = r.crashed[i];
      const double floor = (0.0 - speed) / dt;
      if (!crashed && acc < floor) acc = floor;
      if (crashed) steer = 0, acc = -1.0 * speed;
      if (speed > c_.speed_limit) acc = std::min(acc, 1.0 * (c_.speed_limit - speed));
      else if (speed < 0) acc = std::max(acc, 1.0 * (0.0 - speed));
      const double beta = steer == 0 ? 0.0 : std::atan(1.0 / 2 * std::tan(steer));
      const double angle = r.heading[i] + beta;
      double x = r.x[i] + speed * (angle == 0 ? 1.0 : std::cos(angle)) * dt;
      double y = r.y[i] + speed * (angle == 0 ? 0.0 : std::sin(angle)) * dt;
      if (r.has_impact[i]) {
        x += r.impact_x[i];
        y += r.impact_y[i];
        r.crashed[i] = true;
        r.has_impact[i] = false;
      }
      const double heading =
          r.heading[i] + speed * (beta == 0 ? 0.0 : std::sin(beta)) / (c_.length / 2) * dt;
      r.x[i] = static_cast<T>(x);
      r.y[i] = static_cast<T>(y);
      r.heading[i] = static_cast<T>(heading);
      r.speed[i] = static_cast<T>(speed + acc * dt);
      r.acc[i] = static_cast<T>(acc);
      r.steer[i] = static_cast<T>(steer);
      r.timer[i] += dt;
      r.lane[i] = closest_lane(r.x[i], r.y[i], r.heading[i], r.lane[i]);
    }
  }

  // utils.are_polygons_intersecting for two rectangles (a moving relative to b over dt)
  void sat(const Road<T>& r, int64_t a, int64_t b, bool* hit, bool* will, double* tx,
           double* ty) const {
    const double ax = r.x[a], ay = r.y[a], bx = r.x[b], by = r.y[b];
    const double ca = std::cos(r.heading[a]), sa = std::sin(r.heading[a]);
    const double cb = std::cos(r.heading[b]), sb = std::sin(r.heading[b]);
    const double dispx = (r.speed[a] * ca - r.speed[b] * cb) * c_.dt;
    const double dispy = (r.speed[a] * sa - r.speed[b] * sb) * c_.dt;
    const double normals[4][2] = {{-ca, -sa}, {-sa, ca}, {-cb, -sb}, {-sb, cb}};
    *hit = *will = true;
    double best = std::numeric_limits<double>::infinity();
    for (const auto& nrm : normals) {
      const double nx = nrm[0], ny = nrm[1];
      const double ha = blen_[a] / 2 * std::abs(ca * nx + sa * ny) +
                        bwid_[a] / 2 * std::abs(-sa * nx + ca * ny);
      const double hb = blen_[b] / 2 * std::abs(cb * nx + sb * ny) +
                        bwid_[b] / 2 * std::abs(-sb * nx + cb * ny);
      double min_a = ax * nx + ay * ny - ha, max_a = ax * nx + ay * ny + ha;
      const double min_b = bx * nx + by * ny - hb, max_b = bx * nx + by * ny + hb;
      if ((min_a < min_b ? min_b - max_a : min_a - max_b) > 0) *hit = false;
      const double sweep = nx * dispx + ny * dispy;
      if (sweep < 0) min_a += sweep; else max_a += sweep;
      const double distance = min_a < min_b ? min_b - max_a : min_a - max_b;
      if (distance > 0) *will = false;
      if (std::abs(distance) < best) {
        best = std::abs(distance);
        const double sign = ((ax - bx) * nx + (ay - by) * ny) > 0 ? 1.0 : -1.0;
        *tx = sign * nx;
        *ty = sign * ny;
      }
    }
    *tx *= best;
    *ty *= best;
  }

  void collide(Road<T>& r) {
    // candidate pairs that pass highway-env's spherical pre-check (its first body is the
    // lower index), visited in highway-env's order (i, j), i < j, row by row
    pairs_.clear();
    for (int64_t i = 0; i < n_; ++i) {
      if (obstacle_[i] || !r.present[i]) continue;
      const int64_t partners[5] = {front_[3 * i + 1], front_[3 * i], rear_[3 * i],
                                   front_[3 * i + 2], rear_[3 * i + 2]};
      for (int64_t p : partners) {
        if (p < 0) continue;
        const int64_t a = std::min(i, p), b = std::max(i, p);
        const double dx = static_cast<double>(r.x[b]) - r.x[a];
        const double dy = static_cast<double>(r.y[b]) - r.y[a];
        const double reach = (diag_[a] + diag_[b]) / 2 + r.speed[a] * c_.dt;
        if (std::sqrt(dx * dx + dy * dy) <= reach) pairs_.push_back(a * n_ + b);
      }
    }
    std::sort(pairs_.begin(), pairs_.end());
    pairs_.erase(std::unique(pairs_.begin(), pairs_.end()), pairs_.end());
    for (int64_t key : pairs_) {
      const int64_t a = key / n_, b = key % n_;
      bool hit, will;
      double tx = 0, ty = 0;
      sat(r, a, b, &hit, &will, &tx, &ty);
      if (will) {
        if (obstacle_[b]) {
          r.impact_x[a] = static_cast<T>(tx), r.impact_y[a] = static_cast<T>(ty);
          r.has_impact[a] = true;
        } else {
          r.impact_x[a] = static_cast<T>(tx / 2), r.impact_y[a] = static_cast<T>(ty / 2);
          r.impact_x[b] = static_cast<T>(-tx / 2), r.impact_y[b] = static_cast<T>(-ty / 2);
          r.has_impact[a] = r.has_impact[b] = true;
        }
      }
      if (hit) {
        r.crashed[a] = true;
        if (!obstacle_[b]) r.crashed[b] = true;
      }
    }
  }

  // FreewayEnv's end of a policy step: comfort (eq. 9), the road's mean speed and comfort, the
  // CAVs' observations and rewards (eq. 10), crashed CAVs and vehicles leaving the road
  void finish(Road<T>& r, const Finish& e, const int64_t* slot, bool* alive, const T* abs_acc,
              const bool* lane_change, const bool* crashed_now, float* obs, T* reward,
              T* velocity, T* mean_comfort, double* speed_sum, double* comfort_sum,
              double* samples, int64_t agents, int64_t frames) {
    int64_t count = 0;
    double speeds = 0, comforts = 0;
    for (int64_t i = 0; i < n_; ++i) {
      double comfort = static_cast<double>(abs_acc[i]) / frames < e.comfort_threshold ? 3 : 2;
      if (lane_change[i]) comfort = e.lane_change_comfort;
      if (r.cav[i] && (r.decision[i] == 1 || r.decision[i] == 2)) comfort = e.lane_change_comfort;
      if (r.cav[i] && r.decision[i] == 3) comfort = 0;
      comfort_[i] = comfort;
      if (r.present[i] && !obstacle_[i]) {
        ++count;
        speeds += r.speed[i];
        comforts += comfort;
      }
    }
    const double n_count = std::max<int64_t>(count, 1);
    *velocity = static_cast<T>(speeds / n_count);
    *mean_comfort = static_cast<T>(comforts / n_count);
    *speed_sum += speeds;
    *comfort_sum += comforts;
    *samples += count;
    const int64_t dim = e.merge ? 24 : 22;
    double paid = 0, total = 0;
    for (int64_t a = 0; a < agents; ++a) {
      const int64_t v = slot[a];
      double value = e.velocity_weight * static_cast<double>(r.speed[v]) + comfort_[v];
      if (crashed_now[a]) value = e.collision_reward;
      reward[a] = static_cast<T>(value);
      if (alive[a]) paid += 1, total += reward[a];
      float* o = obs + a * dim;
      std::fill(o, o + dim, 0.0f);
      if (!alive[a]) continue;
      double s, lat;
      local(r.x[v], r.y[v], r.lane[v], &s, &lat);
      o[0] = static_cast<float>(r.speed[v]);
      o[1] = static_cast<float>(l_.number[r.lane[v]]);
      o[2] = static_cast<float>(lat);
      o[3] = static_cast<float>(r.acc[v]);
      const int64_t own = l_.table[r.lane[v]];
      for (int k = 0; k < 3; ++k) {
        const bool lane_ok = own + k - 1 >= 0 && own + k - 1 < c_.n_tables;
        const int64_t others[2] = {front_[3 * v + k], rear_[3 * v + k]};
        for (int j = 0; j < 2; ++j) {
          float* cell = o + 4 + 6 * k + 3 * j;
          const int64_t other = others[j];
          const double dx = other >= 0 ? static_cast<double>(r.x[other]) - r.x[v] : 0.0;
          if (lane_ok && other >= 0 && !obstacle_[other] && std::abs(dx) <= e.perception) {
            cell[0] = 1.0f;
            cell[1] = static_cast<float>(dx);
            cell[2] = static_cast<float>(static_cast<double>(r.speed[other]) - r.speed[v]);
          } else {
            cell[1] = static_cast<float>(j == 0 ? e.perception : -e.perception);
          }
        }
      }
      if (e.merge) {
        o[22] = static_cast<float>(clip(e.merge_start - r.x[v], -e.perception, e.perception));
        o[23] = static_cast<float>(clip(e.merge_end - r.x[v], -e.perception, e.perception));
      }
    }
    if (e.team_reward && paid > 0) {
      for (int64_t a = 0; a < agents; ++a) reward[a] = static_cast<T>(total / paid);
    }
    for (int64_t a = 0; a < agents; ++a) {
      if (!alive[a]) reward[a] = 0;
      alive[a] = alive[a] && !crashed_now[a];
    }
    for (int64_t i = 0; i < n_; ++i) r.present[i] = r.present[i] && !r.crashed[i];
  }

  const int64_t* front() const { return front_.data(); }
  const int64_t* rear() const { return rear_.data(); }

 private:
  Constants c_;
  Lanes l_;
  const bool* obstacle_;
  const double *blen_, *bwid_;
  int64_t n_;
  std::vector<int64_t> order_, rank_, upper_, after_, before_, front_, rear_, pairs_;
  std::vector<int64_t> sorted_table_;
  std::vector<double> cos_, sin_, diag_, comfort_;
  int64_t m_ = 0;
};

template <typename T>
void run(std::vector<torch::Tensor> f, torch::Tensor timer, std::vector<torch::Tensor> ints,
         std::vector<torch::Tensor> flags, std::vector<torch::Tensor> lanes_f,
         std::vector<torch::Tensor> lanes_i, torch::Tensor forbidden, torch::Tensor obstacle,
         torch::Tensor body_length, torch::Tensor body_width, std::vector<double> k,
         std::vector<int64_t> ki, torch::Tensor slot, torch::Tensor acting, torch::Tensor abs_acc,
         torch::Tensor lane_change, torch::Tensor distance, torch::Tensor crashed_now,
         torch::Tensor front_out, torch::Tensor rear_out, int64_t frames,
         std::vector<double> finish, torch::Tensor alive, torch::Tensor obs, torch::Tensor reward,
         torch::Tensor velocity, torch::Tensor comfort, torch::Tensor speed_sum,
         torch::Tensor comfort_sum, torch::Tensor samples) {
  const Finish e{finish[0], finish[1], finish[2],      finish[3], finish[4],
                 finish[5], finish[8], finish[6] != 0, finish[7] != 0};
  const Constants c{k[0],  k[1],  k[2],  k[3],  k[4],  k[5],  k[6],  k[7],  k[8],  k[9],
                    k[10], k[11], k[12], k[13], k[14], k[15], k[16], k[17], k[18], ki[0],
                    ki[1], ki[2] != 0};
  const Lanes l{lanes_f[0].data_ptr<double>(), lanes_f[1].data_ptr<double>(),
                lanes_f[2].data_ptr<double>(), lanes_f[3].data_ptr<double>(),
                lanes_f[4].data_ptr<double>(), lanes_f[5].data_ptr<double>(),
                forbidden.data_ptr<bool>(),    lanes_i[0].data_ptr<int64_t>(),
                lanes_i[1].data_ptr<int64_t>(), lanes_i[2].data_ptr<int64_t>(),
                lanes_i[3].data_ptr<int64_t>(), lanes_i[4].data_ptr<int64_t>(),
                lanes_f[0].numel()};
  const int64_t rows = timer.size(0), n = timer.size(1), agents = slot.size(1);
  Stepper<T> stepper(c, l, obstacle.data_ptr<bool>(), body_length.data_ptr<double>(),
                     body_width.data_ptr<double>(), n);
  for (int64_t b = 0; b < rows; ++b) {
    const int64_t o = b * n;
    Road<T> r{f[0].data_ptr<T>() + o, f[1].data_ptr<T>() + o, f[2].data_ptr<T>() + o,
              f[3].data_ptr<T>() + o, f[4].data_ptr<T>() + o, f[5].data_ptr<T>() + o,
              f[6].data_ptr<T>() + o, f[7].data_ptr<T>() + o, f[8].data_ptr<T>() + o,
              f[9].data_ptr<T>() + o, timer.data_ptr<double>() + o,
              ints[0].data_ptr<int64_t>() + o, ints[1].data_ptr<int64_t>() + o,
              ints[2].data_ptr<int64_t>() + o, flags[0].data_ptr<bool>() + o,
              flags[1].data_ptr<bool>() + o, flags[2].data_ptr<bool>() + o,
              flags[3].data_ptr<bool>() + o, n};
    const int64_t* agent_slot = slot.data_ptr<int64_t>() + b * agents;
    const bool* agent_acting = acting.data_ptr<bool>() + b * agents;
    T* book_acc = abs_acc.data_ptr<T>() + o;
    bool* book_change = lane_change.data_ptr<bool>() + o;
    T* book_distance = distance.data_ptr<T>() + b * agents;
    bool* book_crash = crashed_now.data_ptr<bool>() + b * agents;
    stepper.neighbours(r, true);
    for (int64_t frame = 0; frame < frames; ++frame) {
      stepper.act(r);
      stepper.move(r);
      stepper.neighbours(r, false);
      stepper.collide(r);
      for (int64_t i = 0; i < n; ++i) {
        book_acc[i] += std::abs(r.acc[i]);
        book_change[i] = book_change[i] || (r.lane[i] != r.target[i]);
      }
      for (int64_t a = 0; a < agents; ++a) {
        if (!agent_acting[a] || book_crash[a]) continue;
        const int64_t v = agent_slot[a];
        book_distance[a] += r.speed[v] * static_cast<T>(c.dt);
        book_crash[a] = r.crashed[v];
      }
    }
    std::copy(stepper.front(), stepper.front() + 3 * n, front_out.data_ptr<int64_t>() + 3 * o);
    std::copy(stepper.rear(), stepper.rear() + 3 * n, rear_out.data_ptr<int64_t>() + 3 * o);
    stepper.finish(r, e, agent_slot, alive.data_ptr<bool>() + b * agents, book_acc, book_change,
                   book_crash, obs.data_ptr<float>() + b * agents * obs.size(2),
                   reward.data_ptr<T>() + b * agents, velocity.data_ptr<T>() + b,
                   comfort.data_ptr<T>() + b, speed_sum.data_ptr<double>() + b,
                   comfort_sum.data_ptr<double>() + b, samples.data_ptr<double>() + b, agents,
                   frames);
  }
}

}  // namespace

void policy_step(std::vector<torch::Tensor> f, torch::Tensor timer,
                 std::vector<torch::Tensor> ints, std::vector<torch::Tensor> flags,
                 std::vector<torch::Tensor> lanes_f, std::vector<torch::Tensor> lanes_i,
                 torch::Tensor forbidden, torch::Tensor obstacle, torch::Tensor body_length,
                 torch::Tensor body_width, std::vector<double> k, std::vector<int64_t> ki,
                 torch::Tensor slot, torch::Tensor acting, torch::Tensor abs_acc,
                 torch::Tensor lane_change, torch::Tensor distance, torch::Tensor crashed_now,
                 torch::Tensor front_out, torch::Tensor rear_out, int64_t frames,
                 std::vector<double> finish, torch::Tensor alive, torch::Tensor obs,
                 torch::Tensor reward, torch::Tensor velocity, torch::Tensor comfort,
                 torch::Tensor speed_sum, torch::Tensor comfort_sum, torch::Tensor samples) {
  if (f[0].scalar_type() == torch::kFloat64) {
    run<double>(f, timer, ints, flags, lanes_f, lanes_i, forbidden, obstacle, body_length,
                body_width, k, ki, slot, acting, abs_acc, lane_change, distance, crashed_now,
                front_out, rear_out, frames, finish, alive, obs, reward, velocity, comfort,
                speed_sum, comfort_sum, samples);
  } else {
    run<float>(f, timer, ints, flags, lanes_f, lanes_i, forbidden, obstacle, body_length,
               body_width, k, ki, slot, acting, abs_acc, lane_change, distance, crashed_now,
               front_out, rear_out, frames, finish, alive, obs, reward, velocity, comfort,
               speed_sum, comfort_sum, samples);
  }
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) { m.def("policy_step", &policy_step); }
