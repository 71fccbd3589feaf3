//! The physics (speed and turn-rate limits, sub-stepped), the battery's drain and its failsafe,
//! and the fence's breach and its action.

use super::*;

impl SimAutopilot {
    /// Where the mode sends the vehicle (`None`: stay).
    pub(super) fn destination(&self) -> Option<Vector3<f64>> {
        // A copter on the ground stays there until told to take off (ArduCopter's GUIDED
        // takes no position target as a takeoff).
        if self.landed {
            return None;
        }
        match self.role()? {
            Control::Guided => self.goal,
            Control::Auto => self.mission.get(self.current as usize).map(|i| self.item_position(i)),
            Control::Return => {
                let back = self.at_altitude(self.return_point());
                // ArduCopter's RTL: back at altitude over the return point, then down and land
                // (`ArduCopter/mode_rtl.cpp`); a boat stops there.
                let over = (back - self.pos).xy().norm() < 1e-6;
                Some(match self.spec.frame {
                    Frame::Multirotor if over => Vector3::new(back.x, back.y, self.home.z),
                    _ => back,
                })
            }
            Control::Hold => None,
        }
    }

    /// Advance `dt_wall` wall seconds (`dt_wall * speedup` of simulated flight).
    pub fn step(&mut self, dt_wall: f64) {
        self.wall_s += dt_wall;
        self.sim_s += dt_wall * self.spec.speedup;
        self.update_fix();
        self.report_prearm();
        self.check_auto_disarm(dt_wall * self.spec.speedup);
        self.retry_upload();
        self.run_do_items();
        let mut left = dt_wall * self.spec.speedup;
        let mut moved = 0.0;
        while left > 1e-12 {
            let dt = left.min(SUBSTEP_S);
            left -= dt;
            let before = self.pos;
            // A mission item is reached within WP_RADIUS, and the vehicle goes on to the next;
            // the last one it drives to, and stops at.
            let last = self.current as usize + 1 >= self.mission.len();
            let reached = match (self.armed, self.destination()) {
                (true, Some(goal)) => {
                    self.move_toward(goal, dt) || (!last && (goal - self.pos).norm() <= self.spec.wp_radius)
                }
                _ => false,
            };
            if self.armed {
                self.pos += self.spec.wind.push() * dt;
            }
            self.vel = (self.pos - before) / dt;
            moved += (self.pos - before).norm();
            if reached && self.role() == Some(Control::Auto) {
                self.item_reached();
            }
            self.check_landed();
            self.check_fence();
        }
        // Draw by how fast it went, as a share of its top speed.
        let sim_s = dt_wall * self.spec.speedup;
        self.draw_a = match self.armed {
            false => IDLE_DRAW_A,
            true if sim_s > 0.0 => {
                ARMED_DRAW_A + (MAX_DRAW_A - ARMED_DRAW_A) * (moved / sim_s / self.spec.max_speed).clamp(0.0, 1.0)
            }
            true => ARMED_DRAW_A,
        };
        self.consumed_mah += self.draw_a * sim_s / 3.6;
        self.check_battery();
    }

    /// A copter returning that has come down at its return point has landed, and disarms
    /// (ArduCopter disarms on landing at the end of RTL).
    fn check_landed(&mut self) {
        let down = self.pos.z >= self.home.z - 1e-9;
        if self.spec.frame == Frame::Multirotor
            && self.armed
            && !self.landed
            && down
            && self.role() == Some(Control::Return)
        {
            self.landed = true;
            self.armed = false;
            self.say(MavSeverity::MAV_SEVERITY_INFO, "Disarming motors");
        }
    }

    /// The charge left (mAh).
    pub fn remaining_mah(&self) -> f64 {
        (self.spec.safety.battery_mah - self.consumed_mah).max(0.0)
    }

    /// Below the low mark, armed: the battery failsafe's action, once.
    pub(super) fn check_battery(&mut self) {
        if self.failsafe.is_some() || !self.armed || self.remaining_mah() > self.spec.safety.battery_low_mah {
            return;
        }
        let action = self.spec.safety.low_battery_action;
        self.failsafe = Some("battery low");
        self.act_on(action);
        let text = format!(
            "Failsafe: battery low ({:.0} mAh left): {}",
            self.remaining_mah(),
            ["continue", "RTL", "HOLD"][action as usize]
        );
        self.say(MavSeverity::MAV_SEVERITY_CRITICAL, &text);
    }

    /// A failsafe's action: the mode it calls for (none for `Continue`).
    pub(super) fn act_on(&mut self, action: Action) {
        match action {
            Action::Rtl => self.set_mode(self.spec.frame.mode(Control::Return)),
            Action::Hold => self.set_mode(self.spec.frame.hold_mode()),
            Action::Continue => true,
        };
    }

    /// Where RTL goes, at cruise altitude: the nearest of the rally points, and of home with
    /// `RALLY_INCL_HOME = 1` (ArduPilot's default), or home when there are none.
    pub(super) fn return_point(&self) -> Vector3<f64> {
        let home = Vector3::new(self.home.x, self.home.y, -self.spec.cruise_alt);
        let with_home = self.rally.is_empty() || self.spec.safety.rally_include_home;
        self.rally
            .iter()
            .map(|r| {
                let mut p = self.item_position(r);
                p.z = -self.spec.cruise_alt;
                p
            })
            .chain(with_home.then_some(home))
            .min_by(|a, b| (a - self.pos).xy().norm().total_cmp(&(b - self.pos).xy().norm()))
            .unwrap_or(home)
    }

    /// A breach of the enforced fence triggers the fence action once; back inside, it is over.
    /// What an operator hears of it is ArduPilot's: a rover says nothing (`Rover/fence.cpp`
    /// only changes mode), a copter says "Polygon fence breached" at NOTICE
    /// (`AC_Fence::print_fence_message`); both report it in FENCE_STATUS.
    pub(super) fn check_fence(&mut self) {
        let out = self.fenced_out(&self.pos);
        if out && !self.breached {
            self.breach_count = self.breach_count.saturating_add(1);
            self.act_on(self.spec.safety.fence_action);
            if self.spec.frame == Frame::Multirotor {
                self.say(MavSeverity::MAV_SEVERITY_NOTICE, "Polygon fence breached");
            }
        }
        self.breached = out;
    }

    /// One physics step toward `goal`; whether it is reached.
    pub(super) fn move_toward(&mut self, goal: Vector3<f64>, dt: f64) -> bool {
        let d = goal - self.pos;
        let dist = d.norm();
        let reach = self.spec.max_speed * dt;
        if dist <= 1e-9 {
            return true;
        }
        match self.spec.frame {
            Frame::Multirotor => {
                self.heading = d.y.atan2(d.x);
                if dist <= reach {
                    self.pos = goal;
                    return true;
                }
                self.pos += d * (reach / dist);
            }
            Frame::Boat => {
                let err = wrap(d.y.atan2(d.x) - self.heading);
                let turn = err.clamp(-self.spec.turn_rate * dt, self.spec.turn_rate * dt);
                self.heading = wrap(self.heading + turn);
                let left = err - turn;
                if dist <= reach && left.abs() < PI / 2.0 {
                    self.pos = goal;
                    return true;
                }
                // Pivot (stop and turn) when the goal is more than the pivot angle off the bow;
                // under it, drive on: slowed in the turn, but never below the speed at which the
                // turn rate sweeps the turning radius (an arc, not a pivot).
                let step = if left.abs() > PIVOT_ANGLE_DEG.to_radians() {
                    0.0
                } else {
                    let arc = (self.spec.turn_rate * self.spec.turn_radius * dt).min(reach);
                    (reach * left.cos()).max(if dist > 2.0 * self.spec.turn_radius { arc } else { 0.0 })
                };
                self.pos += Vector3::new(self.heading.cos(), self.heading.sin(), 0.0) * step;
            }
        }
        false
    }
}
