//! Whether a frame runs on the team of threads or on the calling thread
//! alone ([`ModeChoice`]): the frame loop (`frame.rs`) asks before each
//! attempt and reports its cost after it.

/// The team or the calling thread alone, whichever is faster here and now.
///
/// On free cores a team of two runs a 4k-particle 2D substep 1.8× faster
/// than one thread, but when the machine has fewer free cores than the team
/// has threads (another process, or other solvers in this one, are busy),
/// its members keep waiting for each other to be scheduled and the same
/// substep became ~5× slower than one thread (measured, `yes` hogging one of
/// two cores). So each mode's cost per particle-substep is tracked, the
/// cheaper one runs, and now and then four frames run the other to keep its
/// estimate current ("probes"). A mode's cost is the median of its last
/// `WINDOW` attempts: single slow frames (another process waking up, a page
/// fault) do not count, but a way of running that is slow in most frames
/// does. (The lowest was tried first: it kept a team whose frames alternated
/// between 1.4 and 9.9 ms, when the thread pool had gone idle between frames
/// and its second core was slow to come back, against 2.4 ms alone; the mean
/// sent a team alone for 50 frames after one 10 ms frame.) The first `SKIP`
/// attempts are not counted (they allocate the buffers and wake the pool,
/// and measured up to 4× slower than the next ones).
///
/// The first probe comes at attempt `FIRST_PROBE`; after a probe that
/// confirms the choice the next one waits twice as long (from `GAP` up to
/// `MAX_GAP` attempts: a probe of the slower mode costs time), and at least
/// `PROBE_COST_RATIO` times the probe's excess time, counted in frames of the
/// cheaper mode (up to `MAX_COST_GAP`: a small frame's team probe, mostly
/// the pool waking, costs many of its frames); after one
/// that changes it, `GAP` or, if the solver has made fewer attempts, that
/// many (on this VM the pool's first team frames after a while alone took
/// 5 ms where the next took 1, long enough to send a new solver's team alone
/// for `GAP` frames; `a_choice_made_while_the_pool_wakes_is_checked_soon`);
/// and when the team's cost rises past `DEGRADED` times what it was at the
/// last probe (the machine got busy), the probe of the thread alone comes at
/// once (the thread alone getting slower is no reason to try the team: a
/// busy machine slows the team more). Results are the same in both modes.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct ModeChoice {
    /// The last `WINDOW` costs per particle-substep [s] of `[solo, team]`
    /// (0: none yet).
    recent: [[f64; WINDOW]; 2],
    /// Each mode's cost when the last probe ended (0: none yet).
    baseline: [f64; 2],
    attempts: u64,
    /// The attempt at which the next probe starts (0: `FIRST_PROBE`).
    next_probe: u64,
    /// Attempts between the last probe and the next (0: `GAP`).
    gap: u64,
    /// Counted attempts left in the probe under way (0: none), and its mode.
    probe_left: u8,
    /// Wall seconds and attempts of the probe under way (warm-up included).
    probe_secs: f64,
    probe_attempts: u32,
    /// The warm-up under way (a solver's first attempts, a probe's, or the
    /// team's after attempts alone): its attempts and wall seconds so far
    /// (`None`: none under way).
    warm: Option<(u8, f64)>,
    /// Whether the last attempt ran on the team.
    last_team: bool,
    probed_team: bool,
    /// Attempts run `[alone, by the team]` (probes included; all alone on a
    /// pool of one thread): [`Solver::mode_runs`](super::Solver::mode_runs).
    pub(super) runs: [u64; 2],
    /// Tests: always this mode.
    #[cfg(test)]
    pub(super) force: Option<bool>,
}

const FIRST_PROBE: u64 = 8;
/// Attempts per probe, of which the first `PROBE_WARMUP` are not counted:
/// after frames alone, the pool's first frames wake it, and on this VM the
/// first two team frames measured 10 and 5 ms where the third took 1.3
/// (the README's hybrid run, after its network steps).
const PROBE_LEN: u8 = 4;
const PROBE_WARMUP: u8 = 2;
/// A warm-up of the team (its first `SKIP` attempts in a solver, the first
/// `PROBE_WARMUP` of a probe, the first `PROBE_WARMUP` after attempts
/// alone) goes on until it has lasted this long [s], up to `WARMUP_MAX`
/// attempts: on this VM the pool's second core, idle for a
/// while, took 10–40 ms to come back (water3d, 4k particles, new solvers:
/// two to seven team frames of 5 ms, then 1.1 ms; alone 1.9 ms).
const WAKE_SECS: f64 = 0.05;
const WARMUP_MAX: u8 = 8;
const GAP: u64 = 50;
const MAX_GAP: u64 = 400;
const SKIP: u64 = 2;
const WINDOW: usize = 8;
const DEGRADED: f64 = 1.5;
/// A probe that lost is followed by at least this many times its excess
/// time (its wall time less what the cheaper mode would have taken) in
/// attempts of the cheaper mode, so that probing costs at most about 2% of
/// the time: small frames (a few hundred particles, 0.3 ms) paid a team
/// probe of ~10 slow frames (the pool's wake-up) every 400 attempts, 38% of
/// their time on a busy machine (water2d on 64², 400 frames) ...
const PROBE_COST_RATIO: f64 = 50.0;
/// ... up to this many attempts.
const MAX_COST_GAP: u64 = 20_000;
/// The thread alone runs only when its cost is below this fraction of the
/// team's (timings are noisy).
const SOLO_MARGIN: f64 = 0.9;

impl ModeChoice {
    /// The estimated cost of a mode (0: unknown).
    fn cost(&self, team: bool) -> f64 {
        let mut v = [0.0f64; WINDOW];
        let mut n = 0;
        for &c in self.recent[team as usize].iter().filter(|&&c| c > 0.0) {
            v[n] = c;
            n += 1;
        }
        let v = &mut v[..n];
        v.sort_by(f64::total_cmp);
        match n {
            0 => 0.0,
            _ if n % 2 == 1 => v[n / 2],
            _ => 0.5 * (v[n / 2 - 1] + v[n / 2]),
        }
    }

    /// The cheaper mode as measured (the team while either is unknown).
    fn best_is_team(&self) -> bool {
        let (solo, team) = (self.cost(false), self.cost(true));
        !(solo > 0.0 && team > 0.0 && solo < SOLO_MARGIN * team)
    }

    fn next_probe(&self) -> u64 {
        if self.next_probe == 0 {
            FIRST_PROBE
        } else {
            self.next_probe
        }
    }

    /// Whether the next attempt uses the team, and whether it is a probe.
    pub(super) fn choose(&self) -> (bool, bool) {
        #[cfg(test)]
        if let Some(team) = self.force {
            return (team, false);
        }
        let best = self.best_is_team();
        if self.probe_left > 0 {
            (self.probed_team, true)
        } else if self.attempts >= self.next_probe() {
            (!best, true)
        } else {
            (best, false)
        }
    }

    /// Record an attempt's cost per particle-substep [s] and its wall time
    /// [s] (the mode and probe flag that `choose` gave it).
    pub(super) fn record(&mut self, team: bool, probe: bool, seconds_per_item: f64, seconds: f64) {
        let m = team as usize;
        if self.attempts == 0 {
            self.warm = Some((0, 0.0));
        }
        let starts = probe && self.probe_left == 0;
        if starts {
            // a probe starts its mode's window afresh (older samples are stale)
            self.recent[m] = [0.0; WINDOW];
            self.probe_left = PROBE_LEN - PROBE_WARMUP;
            self.probed_team = team;
            (self.probe_secs, self.probe_attempts) = (0.0, 0);
        }
        if probe {
            self.probe_secs += seconds;
            self.probe_attempts += 1;
        }
        if starts || (team && !self.last_team && self.attempts > 0) {
            // the pool has been idle if the thread ran alone: wake it first
            self.warm = Some((0, 0.0));
        }
        self.last_team = team;
        let least = if self.attempts < SKIP {
            SKIP as u8
        } else {
            PROBE_WARMUP
        };
        // (only the team's warm-up waits for the pool: the thread alone is
        // the caller's, already running)
        let warmup = match self.warm {
            Some((n, secs)) => n < least || (team && secs < WAKE_SECS && n < WARMUP_MAX),
            None => false,
        };
        self.warm = match self.warm {
            Some((n, secs)) if warmup => Some((n + 1, secs + seconds)),
            _ => None,
        };
        if !warmup {
            let w = &mut self.recent[m];
            w.rotate_right(1);
            w[0] = seconds_per_item;
        }
        let probe_ends = probe && !warmup && {
            self.probe_left -= 1;
            self.probe_left == 0
        };
        self.attempts += 1;
        let gap = if self.gap == 0 { GAP } else { self.gap };
        if probe_ends {
            // the probe lost: wait longer for the next one; it won: soon,
            // and sooner in a solver's first frames (a choice made while the
            // pool was waking up is checked again after as many attempts as
            // it was made after)
            self.gap = if self.best_is_team() != team {
                // what the probe cost above the cheaper mode's frames (this
                // attempt's items at the cheaper mode's cost per item)
                let best = self.cost(!team);
                let best_secs = best * seconds / seconds_per_item.max(f64::MIN_POSITIVE);
                let excess = self.probe_secs - self.probe_attempts as f64 * best_secs;
                let by_cost = if best_secs > 0.0 && excess > 0.0 {
                    ((PROBE_COST_RATIO * excess / best_secs).ceil() as u64).min(MAX_COST_GAP)
                } else {
                    0
                };
                (2 * gap).min(MAX_GAP).max(by_cost)
            } else {
                GAP.min(self.attempts)
            };
            self.next_probe = self.attempts + self.gap;
            self.baseline = [self.cost(false), self.cost(true)];
        } else if !probe
            && team
            && self.baseline[m] > 0.0
            && self.cost(team) > DEGRADED * self.baseline[m]
            && self.best_is_team() == team
        {
            // the running mode got slower (and still looks the cheaper):
            // measure the other one now
            self.next_probe = self.next_probe().min(self.attempts);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Run `n` attempts at the given costs per mode; returns how many were
    /// probes.
    fn attempts(m: &mut ModeChoice, n: usize, solo: f64, team: f64) -> usize {
        let mut probes = 0;
        for _ in 0..n {
            let (t, probe) = m.choose();
            probes += probe as usize;
            let c = if t { team } else { solo };
            m.record(t, probe, c, c);
        }
        probes
    }

    #[test]
    fn the_frames_of_a_waking_pool_are_not_counted() {
        // the team's first five frames take 5 ms (the pool's second core
        // comes back), and its first two after frames alone, then 1.1 ms;
        // alone 1.9 ms: the thread alone runs only in probes
        let mut m = ModeChoice::default();
        let (mut team_frames, mut since_alone, mut alone) = (0, 0, 0);
        for _ in 0..200 {
            let (t, probe) = m.choose();
            let c = if t {
                team_frames += 1;
                since_alone += 1;
                if team_frames <= 5 || since_alone <= 2 {
                    0.005
                } else {
                    0.0011
                }
            } else {
                alone += !probe as usize;
                since_alone = 0;
                0.0019
            };
            m.record(t, probe, c, c);
        }
        assert_eq!(m.choose(), (true, false));
        assert_eq!(alone, 0, "attempts alone outside probes");
    }

    /// Small frames (one unit alone) whose team frames cost five units (the
    /// pool waking on a busy machine): probing the team costs a few percent
    /// of the time, not the 10-40% that probes every `MAX_GAP` attempts
    /// cost, and the thread alone getting slower does not trigger a probe.
    #[test]
    fn probes_of_a_losing_team_cost_little_time() {
        let mut m = ModeChoice::default();
        let (mut total, mut alone) = (0.0, 0.0);
        for i in 0..20_000 {
            let (t, probe) = m.choose();
            // the thread alone slows down now and then (another process)
            let solo = if (i / 500) % 2 == 1 { 2.0 } else { 1.0 };
            let c = if t { 5.0 * solo } else { solo };
            total += c;
            alone += if t { 0.0 } else { c };
            m.record(t, probe, c, c);
        }
        assert_eq!(m.choose(), (false, false));
        let share = (total - alone) / total;
        assert!(share < 0.04, "team frames took {share:.3} of the time");
    }

    #[test]
    fn a_choice_made_while_the_pool_wakes_is_checked_soon() {
        // the team's first frames are slow (the pool wakes), then it is
        // twice as fast as the thread alone: the thread alone wins the first
        // probe, and the team is back within about as many attempts again
        let mut m = ModeChoice::default();
        attempts(&mut m, FIRST_PROBE as usize, 2.0, 5.0);
        attempts(&mut m, PROBE_LEN as usize, 2.0, 1.0);
        assert_eq!(m.choose(), (false, false));
        let n = (FIRST_PROBE as usize + PROBE_LEN as usize) + PROBE_LEN as usize;
        attempts(&mut m, n, 2.0, 1.0);
        assert_eq!(m.choose(), (true, false));
        assert!(m.attempts < GAP, "{}", m.attempts);
    }

    #[test]
    fn the_cheaper_mode_runs_and_the_other_is_probed() {
        let mut m = ModeChoice::default();
        // nothing measured: the team; the first attempts are not counted
        for _ in 0..SKIP {
            assert_eq!(m.choose(), (true, false));
            m.record(true, false, 100.0, 100.0);
        }
        assert_eq!((m.cost(false), m.cost(true)), (0.0, 0.0));
        // the team's cost: the median of its recent attempts (one slow
        // frame does not count)
        for cost in [1.5, 0.5, 9.0, 0.9, 1.0, 1.0] {
            assert_eq!(m.choose(), (true, false));
            m.record(true, false, cost, cost);
        }
        assert_eq!(m.cost(true), 1.0);
        // four attempts probe the thread alone (the first two, which wake
        // the pool in a team's probe, do not count: 1.3 and 1.1 stay out of the
        // median); only slightly cheaper, it does not win
        for cost in [1.3, 1.1, 0.9, 1.0] {
            assert_eq!(m.choose(), (false, true));
            m.record(false, true, cost, cost);
        }
        assert_eq!(m.cost(false), 0.95);
        assert_eq!(m.choose(), (true, false));
        // probes that confirm the choice come ever less often: each waits
        // twice the last gap (from 2·GAP after the first) up to MAX_GAP
        let mut starts = Vec::new();
        for _ in 0..1500 {
            let (t, probe) = m.choose();
            if probe && m.probe_left == 0 {
                starts.push(m.attempts);
            }
            let c = if t { 1.0 } else { 2.0 };
            m.record(t, probe, c, c);
        }
        let len = PROBE_LEN as u64;
        assert_eq!(starts[0], FIRST_PROBE + len + 2 * GAP);
        let gaps: Vec<u64> = starts.windows(2).map(|w| w[1] - w[0] - len).collect();
        assert_eq!(gaps, [4 * GAP, MAX_GAP, MAX_GAP]);
        // the machine gets busy (the team's cost rises past DEGRADED × its
        // baseline, a probe follows): within a window and a probe of
        // attempts the thread alone runs
        attempts(&mut m, WINDOW + 2, 1.5, 5.0);
        assert_eq!(m.choose(), (false, false));
        // the team is cheaper again: within MAX_GAP and a probe it runs
        attempts(&mut m, MAX_GAP as usize + PROBE_LEN as usize, 1.5, 0.5);
        assert_eq!(m.choose(), (true, false));
        // and a solver whose team was never cheaper stays alone
        let mut m = ModeChoice::default();
        let len = PROBE_LEN as usize;
        assert!(attempts(&mut m, 1000, 1.0, 5.0) <= len + len * 1000 / (2 * GAP as usize));
        assert_eq!(m.choose(), (false, false));
    }
}
