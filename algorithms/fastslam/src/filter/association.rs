//! Data association, weighing and the landmark updates of one particle for one frame (FastSLAM
//! 2.0's proposal when `proposal = "optimal"`), and the stereo candidates of an observation.

use super::*;

// Decisions live in a short per-particle Vec; boxing the large variant would cost an allocation
// per matched observation in the hottest loop.
#[allow(clippy::large_enum_variant)]
pub(super) enum Association {
    Matched(u32, Fit),
    Ambiguous,
    /// An attribute match outside the χ² gate.
    Rejected,
    New,
}

/// What the weighing needs of a match: of the innovation ν, the Cholesky factor of S and
/// νᵀS⁻¹ν; of the landmark, its hits and mean (kept so the map is not searched for it again).
/// A third of an [`Innovation`] and its landmark's size: ~700 of them per particle and frame.
#[derive(Debug, Clone, Copy)]
pub(super) struct Fit {
    nu: Vector3<f64>,
    chol: Chol3,
    mahalanobis: f64,
    hits: u32,
    mean_m: Vector3<f64>,
}

impl Fit {
    fn new(inn: &Innovation, lm: &ekf::LandmarkEkf) -> Self {
        Self { nu: inn.nu, chol: *inn.chol(), mahalanobis: inn.mahalanobis, hits: lm.hits, mean_m: lm.mean_m }
    }

    /// ln N(ν; 0, S) (as [`Innovation::log_likelihood`]).
    fn log_likelihood(&self) -> f64 {
        -0.5 * (self.mahalanobis + self.chol.log_det() + 3.0 * (2.0 * std::f64::consts::PI).ln())
    }
}

/// A particle's association decision for one observation, kept between weighing and updating.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Decision {
    Matched(u32),
    Ambiguous,
    Rejected,
    New,
}

impl FastSlam {
    /// Associates one observation for one particle (EQUATIONS §3): by feature track id when the
    /// observation has one, else by descriptor with a ratio test when it has one, else by
    /// maximum likelihood; every association inside the χ²₃ gate. The gate's covariance is the
    /// innovation covariance plus `pose_q` = H_x·P·H_xᵀ, the pose uncertainty of this frame's
    /// motion seen in the observation: a particle's pose is one sample of it, and with a sensor
    /// more precise than the motion a gate without it would refuse the right landmark.
    pub(super) fn associate(
        cfg: &FastSlamConfig,
        candidates: &[u32],
        p: &Particle,
        view: &View,
        o: &Observation,
        pose_q: &(Matrix3<f64>, Matrix3<f64>),
        by_track: bool,
    ) -> Association {
        let (pose_q, pose_q_body) = (&pose_q.0, &pose_q.1);
        let a = &cfg.association;
        let gated = |inn: &Innovation| -> Option<f64> {
            let m = Chol3::new(&(inn.S + pose_q))?.mahalanobis(&inn.nu);
            m.is_finite().then_some(m)
        };
        if by_track {
            // By attribute ([3D] §3.1): the landmark of this feature track, if any, checked
            // against the χ² gate (a tracker's wrong match is left out, not fused).
            for &id in candidates {
                let Some(lm) = p.map.get(id) else { continue };
                return match view.observe(lm, o) {
                    Ok(inn) if gated(&inn).is_some_and(|m| m <= a.gate_chi2) => {
                        Association::Matched(id, Fit::new(&inn, lm))
                    }
                    _ => Association::Rejected,
                };
            }
            return Association::New;
        }
        let w = p.pose.transform_point(&o.z_m.into()).coords;
        let mut ml: Option<(f64, u32, Fit)> = None;
        let mut second_ml = f64::INFINITY;
        let mut near_dup = false;
        let mut best_d: Option<(u32, u32, Fit)> = None; // (hamming, id, fit)
        let mut second_d = u32::MAX;
        let tr_rz = o.Rz.trace() + pose_q_body.trace();
        for &id in candidates {
            let Some(lm) = p.map.get(id) else { continue };
            // Exact pre-check without a Cholesky: |ν| = |w − L| (a rotation keeps lengths) and
            // νᵀS⁻¹ν ≥ |ν|²/λmax(S) ≥ |ν|²/tr(S), with tr(S) = tr(Σ_L) + tr(Rz) + tr(pose_q).
            let d2 = (lm.mean_m - w).norm_squared();
            if d2 > a.duplicate_gate_chi2 * (lm.cov_m2.trace() + tr_rz) {
                continue;
            }
            let Ok(inn) = view.observe(lm, o) else { continue };
            let Some(m) = gated(&inn) else { continue };
            if m > a.duplicate_gate_chi2 {
                continue;
            }
            near_dup = true;
            if m > a.gate_chi2 {
                continue;
            }
            if let (Some(od), Some(ld)) = (&o.descriptor, &lm.descriptor) {
                let d = hamming(od, ld);
                match &best_d {
                    Some((bd, _, _)) if d >= *bd => second_d = second_d.min(d),
                    _ => {
                        if let Some((bd, _, _)) = &best_d {
                            second_d = second_d.min(*bd);
                        }
                        best_d = Some((d, id, Fit::new(&inn, lm)));
                    }
                }
            }
            match &ml {
                Some((mm, _, _)) if m >= *mm => second_ml = second_ml.min(m),
                _ => {
                    if let Some((mm, _, _)) = &ml {
                        second_ml = second_ml.min(*mm);
                    }
                    ml = Some((m, id, Fit::new(&inn, lm)));
                }
            }
        }
        if o.descriptor.is_some() {
            if let Some((d, id, fit)) = best_d
                && d <= a.max_hamming
                && (second_d == u32::MAX || (d as f64) < a.ratio * second_d as f64)
            {
                return Association::Matched(id, fit);
            }
        } else if let Some((m, id, fit)) = ml {
            // Two landmarks about as likely: rather none than maybe the wrong one.
            if second_ml - m >= a.ml_margin_chi2 {
                return Association::Matched(id, fit);
            }
            return Association::Ambiguous;
        }
        if near_dup { Association::Ambiguous } else { Association::New }
    }

    /// Association decisions and the importance weight of one particle for one frame (and, with
    /// the FastSLAM 2.0 proposal, its pose sampled from the proposal); maps are only read.
    ///
    /// FastSLAM 2.0 ([3D] Alg 2 with the proposal of Montemerlo et al. 2003): with the motion
    /// prior N(0, P) on the pose perturbation and the matched confirmed landmarks' innovations
    /// νᵢ ≈ H_{x,i}·δ + noise(Sᵢ), the proposal is N(μ, Σ) with Σ = (P⁻¹ + Σ H_xᵀS⁻¹H_x)⁻¹,
    /// μ = Σ·Σ H_xᵀS⁻¹ν, and the weight is the joint marginal likelihood
    /// N(ν; 0, blockdiag(S) + H_x·P·H_xᵀ), evaluated through the determinant lemma and
    /// Woodbury: ln w = −½(Σ νᵀS⁻¹ν − bᵀΣb + Σ ln|S| + ln|P| − ln|Σ| + 3n ln 2π), b = Σ H_xᵀS⁻¹ν.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn weigh_particle(
        cfg: &FastSlamConfig,
        candidates: &[Vec<u32>],
        order: &[u32],
        known: &[bool],
        pose_q: &[(Matrix3<f64>, Matrix3<f64>)],
        p: &mut Particle,
        obs: &[Observation],
        motion_cov: &Matrix6<f64>,
        rng: &mut Xoshiro256PlusPlus,
    ) -> Vec<Decision> {
        let a = &cfg.association;
        let ln2pi = (2.0 * std::f64::consts::PI).ln();
        let view = View::new(&p.pose, obs);
        // Each observation on its own (in the visiting order, for the memory's sake).
        let mut decisions: Vec<Association> = (0..obs.len()).map(|_| Association::Ambiguous).collect();
        for &j in order {
            let j = j as usize;
            decisions[j] = Self::associate(cfg, &candidates[j], p, &view, &obs[j], &pose_q[j], known[j]);
        }
        // One observation per landmark and frame: of several matched to one landmark the one
        // with the smallest normalised innovation keeps it, the others are left out.
        // (Landmark and observation packed in one u64 and sorted; in each landmark's run the
        // smallest innovation keeps it, the earlier observation on a tie.)
        let mut matched: Vec<u64> = decisions
            .iter()
            .enumerate()
            .filter_map(|(j, d)| match d {
                Association::Matched(id, _) => Some(((*id as u64) << 32) | j as u64),
                _ => None,
            })
            .collect();
        matched.sort_unstable();
        let m_of = |d: &Association| if let Association::Matched(_, fit) = d { fit.mahalanobis } else { f64::INFINITY };
        let mut run = 0;
        while run < matched.len() {
            let id = matched[run] >> 32;
            let end = run + matched[run..].iter().take_while(|k| *k >> 32 == id).count();
            if end - run > 1 {
                let j_of = |k: u64| (k & 0xffff_ffff) as usize;
                let best = (run..end)
                    .min_by(|&a, &b| m_of(&decisions[j_of(matched[a])]).total_cmp(&m_of(&decisions[j_of(matched[b])])))
                    .expect("a run of two or more");
                for k in (run..end).filter(|&k| k != best) {
                    decisions[j_of(matched[k])] = Association::Ambiguous;
                }
            }
            run = end;
        }
        if cfg.proposal == Proposal::Optimal
            && let Some(cP) = Cholesky::new(*motion_cov)
        {
            let mut A = cP.inverse();
            let mut b = Vector6::zeros();
            let mut quad = 0.0;
            let mut log_det_s = 0.0;
            let mut n = 0usize;
            for (d, o) in decisions.iter().zip(obs) {
                let Association::Matched(_, fit) = d else { continue };
                if fit.hits < a.confirm_after {
                    continue;
                }
                // Hxᵀ·S⁻¹·Hx and Hxᵀ·S⁻¹·ν through the whitened W = L⁻¹·Hx (S = L·Lᵀ).
                let W = fit.chol.whiten(&view.pose_jacobian(&fit.mean_m, o));
                A.gemm_tr(1.0, &W, &W, 1.0);
                b.gemv_tr(1.0, &W, &fit.chol.whiten_vector(&fit.nu), 1.0);
                quad += fit.mahalanobis;
                log_det_s += fit.chol.log_det();
                n += 1;
            }
            if n > 0
                && let Some(cA) = Cholesky::new(A)
            {
                let Sigma = cA.inverse();
                let mu = Sigma * b;
                let log_det_p: f64 = cP.l().diagonal().iter().map(|d| 2.0 * d.ln()).sum();
                let log_det_a: f64 = cA.l().diagonal().iter().map(|d| 2.0 * d.ln()).sum();
                let log_w = -0.5 * (quad - b.dot(&mu) + log_det_s + log_det_p + log_det_a + 3.0 * n as f64 * ln2pi);
                if log_w.is_finite() {
                    p.log_w += log_w;
                }
                if let Some(cs) = Cholesky::new(Sigma) {
                    let z = Vector6::from_iterator((0..6).map(|_| rng.sample::<f64, _>(StandardNormal)));
                    let delta = mu + cs.l() * z;
                    if delta.iter().all(|v| v.is_finite()) {
                        p.pose = perturb(&p.pose, &delta);
                    }
                }
            }
        }
        obs.iter()
            .zip(decisions)
            .map(|(o, d)| match d {
                Association::Matched(id, fit) => {
                    if cfg.proposal != Proposal::Optimal && fit.hits >= a.confirm_after {
                        p.log_w += fit.log_likelihood();
                    }
                    Decision::Matched(id)
                }
                Association::Ambiguous => Decision::Ambiguous,
                Association::Rejected => {
                    // Unexplained, like a new landmark: the density at the gate boundary.
                    let log_det = meas_cov(o).determinant().max(1e-300).ln();
                    p.log_w += -0.5 * (a.gate_chi2 + log_det + 3.0 * ln2pi);
                    Decision::Rejected
                }
                Association::New => {
                    // ln p(new): the density at the gate boundary of the observation's own noise.
                    let log_det = meas_cov(o).determinant().max(1e-300).ln();
                    p.log_w += -0.5 * (a.gate_chi2 + log_det + 3.0 * ln2pi);
                    Decision::New
                }
            })
            .collect()
    }

    /// Applies one particle's decisions to its map: landmark EKF updates (at the particle's
    /// current pose), new landmarks, provisional bookkeeping.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn apply_particle(
        cfg: &FastSlamConfig,
        p: &mut Particle,
        obs: &[Observation],
        order: &[u32],
        decisions: &[Decision],
        new_ids: &[Option<u32>],
        frame: u32,
    ) -> ParticleFrame {
        let a = &cfg.association;
        let mut out = ParticleFrame { associations: vec![None; obs.len()], ..Default::default() };
        let view = View::new(&p.pose, obs);
        // Visited in `order` (the memory's sake); what depends on the order is put back in the
        // observations' order below: the NIS sum, the created landmarks and the provisional list.
        let mut nis_of: Vec<(u32, f64)> = vec![];
        let mut anchors = ekf::AnchorMemo::default();
        let first_provisional = p.provisional.len();
        for &j in order {
            let j = j as usize;
            let (o, d) = (&obs[j], &decisions[j]);
            match *d {
                Decision::Matched(id) => {
                    let pose = p.pose;
                    let Some(lm) = p.map.get_mut(id) else { continue };
                    // The update, and the observation's NIS against the landmark before it.
                    let nis = match (&o.stereo, lm.inverse_depth.is_some()) {
                        (Some(st), true) => {
                            match (view.rig_for(o), lm.inverse_depth.as_ref().map(|i| i.world_from_anchor)) {
                                (Some(r), Some(anchor)) => {
                                    ekf::update_inverse_depth_in(lm, anchors.get(&r.camera, &anchor), &st.s, &st.cov, 3)
                                }
                                _ => ekf::update_inverse_depth(lm, &(pose * st.body_from_camera), &st.s, &st.cov, 3),
                            }
                        }
                        (Some(st), false) => {
                            let Ok(inn) = observe(&pose, lm, o) else { continue };
                            ekf::update_stereo_iterated(lm, &(pose * st.body_from_camera), &st.s, &st.cov, 4)
                                .map(|_| inn.mahalanobis)
                        }
                        (None, _) => {
                            let Ok(inn) = observe(&pose, lm, o) else { continue };
                            // A Cartesian observation: the Cartesian view takes over.
                            lm.inverse_depth = None;
                            ekf::update(lm, &inn, &o.Rz).map(|_| inn.mahalanobis)
                        }
                    };
                    let Ok(nis) = nis else { continue };
                    if lm.hits >= a.confirm_after {
                        nis_of.push((j as u32, nis));
                    }
                    lm.hits += 1;
                    lm.last_seen_frame = frame;
                    if lm.hits == a.confirm_after {
                        p.confirmed += 1;
                    }
                    if lm.hits >= a.confirm_after {
                        out.matched += 1;
                    }
                    out.associations[j] = Some(id);
                }
                Decision::Ambiguous => out.ambiguous += 1,
                Decision::Rejected => out.rejected += 1,
                Decision::New => {
                    let Some(id) = new_ids[j] else { continue };
                    let lm = match (&o.stereo, view.rig_for(o)) {
                        (Some(st), Some(r)) => {
                            ekf::init_landmark_inverse_depth_from(&r.camera, &st.s, &st.cov, o.descriptor, frame)
                        }
                        (Some(st), None) => ekf::init_landmark_inverse_depth(
                            &(p.pose * st.body_from_camera),
                            &st.s,
                            &st.cov,
                            o.descriptor,
                            frame,
                        ),
                        (None, _) => init_landmark(&p.pose, &o.z_m, &o.Rz, o.descriptor, frame),
                    };
                    out.created.push((id, j as u32, lm.mean_m));
                    p.map.insert(id, lm);
                    if a.confirm_after <= 1 {
                        p.confirmed += 1;
                    } else {
                        p.provisional.push(id);
                    }
                    out.new += 1;
                }
            }
        }
        // Back in the observations' order (new ids ascend with it).
        nis_of.sort_unstable_by_key(|(j, _)| *j);
        out.nis_sum = nis_of.iter().map(|(_, n)| n).sum();
        out.created.sort_unstable_by_key(|(id, _, _)| *id);
        p.provisional[first_provisional..].sort_unstable();
        // Provisional landmarks: confirmed ones leave the list, stale ones are dropped. Those
        // made in this frame (seen once, now) stay without being looked up.
        let (confirm, max_age) = (a.confirm_after, a.provisional_max_age_frames);
        let fresh = p.provisional.split_off(first_provisional);
        let mut keep = Vec::with_capacity(p.provisional.len() + fresh.len());
        for id in std::mem::take(&mut p.provisional) {
            match p.map.get(id) {
                Some(l) if l.hits >= confirm => {}
                Some(l) if frame - l.last_seen_frame > max_age => {
                    p.map.remove(id);
                }
                Some(_) => keep.push(id),
                None => {}
            }
        }
        keep.extend(fresh);
        p.provisional = keep;
        out
    }

    /// Candidates of the stereo observations without a track id (once for all particles):
    /// every landmark of the local map created within reach of the camera, seen from the best
    /// particle with its estimate there, whose predicted stereo coordinates pass the duplicate
    /// gate (with a margin) of the observation's, the covariance widened by this frame's motion
    /// and the particles' spread; each particle then checks its own candidates exactly.
    pub(super) fn stereo_candidates(
        &self,
        obs: &[Observation],
        known: &[bool],
        motion_cov: &Matrix6<f64>,
        spread: &(Isometry3<f64>, f64, f64),
        out: &mut [Vec<u32>],
    ) {
        let idx: Vec<usize> = (0..obs.len()).filter(|&j| !known[j] && obs[j].stereo.is_some()).collect();
        if idx.is_empty() || self.grid.view.is_empty() {
            return;
        }
        let best = self.best();
        let pose = best.pose;
        let mut cov = *motion_cov;
        for k in 0..3 {
            cov[(k, k)] += spread.1 * spread.1;
            cov[(3 + k, 3 + k)] += spread.2 * spread.2;
        }
        let gate = self.cfg.association.duplicate_gate_chi2 * 1.5;
        // Observations by camera (one camera in practice) and their pose uncertainty in s.
        let mut by_camera: Vec<(Isometry3<f64>, Vec<usize>)> = vec![];
        for &j in &idx {
            let cam = obs[j].stereo.as_ref().expect("filtered").body_from_camera;
            match by_camera.iter_mut().find(|(c, _)| c == &cam) {
                Some((_, v)) => v.push(j),
                None => by_camera.push((cam, vec![j])),
            }
        }
        for (cam, js) in by_camera {
            let world_from_cam = pose * cam;
            // Observation s with their covariance plus the pose term.
            let obs_s: Vec<(Vector3<f64>, Matrix3<f64>)> = js
                .iter()
                .map(|&j| {
                    let o = &obs[j];
                    let st = o.stereo.as_ref().expect("filtered");
                    let l = pose.transform_point(&o.z_m.into()).coords;
                    let Hx = pose_jacobian(&pose, &l, o);
                    let q = Hx * cov * Hx.transpose();
                    (st.s, st.cov + (q + q.transpose()) * 0.5)
                })
                .collect();
            let reach = js
                .iter()
                .map(|&j| obs[j].z_m.norm() + 3.0 * obs[j].Rz.trace().sqrt())
                .fold(0.0f64, f64::max)
                .min(MAX_VIEW_M)
                + VIEW_CELL_M * 3f64.sqrt();
            let grid = SGrid::new(&obs_s);
            let max_var = obs_s.iter().fold([0.0f64; 2], |m, (_, c)| [m[0].max(c[(0, 0)]), m[1].max(c[(1, 1)])]);
            let centre = world_from_cam.translation.vector;
            for (key, ids) in &self.grid.view {
                let c = Vector3::new(key[0] as f64 + 0.5, key[1] as f64 + 0.5, key[2] as f64 + 0.5) * VIEW_CELL_M;
                if (c - centre).norm() > reach {
                    continue;
                }
                for &id in ids {
                    let Some(lm) = best.map.get(id) else { continue };
                    let Some((s, Sl)) = predict_stereo(lm, &world_from_cam) else { continue };
                    let k = gate.sqrt();
                    let ra = k * (Sl[(0, 0)] + max_var[0]).sqrt();
                    let rb = k * (Sl[(1, 1)] + max_var[1]).sqrt();
                    grid.query(s[0], s[1], ra, rb, |i| {
                        let (so, co) = &obs_s[i];
                        let nu = so - s;
                        if let Some(ch) = Chol3::new(&(Sl + co))
                            && ch.mahalanobis(&nu) <= gate
                        {
                            out[js[i]].push(id);
                        }
                    });
                }
            }
        }
    }
}
