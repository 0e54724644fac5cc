//! The bridge as a [`Stage`]: its `out` routes are taps (subscribers) drained into Zenoh
//! publishers at every wake-up; its `in` routes are Zenoh subscribers whose callbacks queue the
//! received bytes and wake the loop through a [`pipeline_runtime::Waker`] (no polling), and the
//! step publishes them into loaned iceoryx2 samples. See the crate docs for keys, policies, the
//! end of stream and what is counted.

use std::collections::{BTreeMap, BTreeSet};
use std::ops::ControlFlow;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use pipeline_runtime::stage::{EndAfter, Ending, Stage, Step};
use pipeline_runtime::topics::Emit;
use pipeline_runtime::{ProcessContext, Restart, Runtime, StageError, Wake};
use shared_types::WireType;
use zenoh::Wait;
use zenoh::qos::CongestionControl;

use crate::clock::ClockProbe;
use crate::counts::*;
use crate::inbox::*;
use crate::order::*;
use crate::routes::*;
use crate::session::*;
use crate::summary::{
    AcceptSummary, BridgePart, BridgeSummary, InRouteSummary, OutRouteSummary, SecuritySummary, TlsSummary,
};
use crate::{BridgeSettings, ClockMode, Policy, ack_key, end_key, key};
use crate::{lock, zenoh_err};
use pipeline_runtime::topics::Origin;

/// The `bridge` stage.
pub struct BridgeStage {
    settings: BridgeSettings,
    session: zenoh::Session,
    outs: Vec<OutRoute>,
    ins: Vec<InRoute>,
    emitters: Vec<Box<dyn Emit>>,
    inbox: Arc<Inbox>,
    /// The robots this bridge receives from, and what each said it sent (once its end marker came).
    ends: BTreeMap<String, Option<BTreeMap<String, u64>>>,
    _end_subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
    /// Set when a receiving bridge acknowledged this bridge's end marker.
    acked: Arc<AtomicBool>,
    _ack_subscriber: Option<zenoh::pubsub::Subscriber<()>>,
    end_acknowledged: Option<bool>,
    published: u64,
    started: Instant,
    /// Answers other bridges' clock asks (when this bridge sends).
    _clock_answers: Option<zenoh::pubsub::Subscriber<()>>,
    /// Per robot received from: its clock (stopped before the session closes).
    clocks: BTreeMap<String, ClockProbe>,
    /// When the counts were last kept for a restart, and the activity they had then.
    kept_at: Option<(Instant, u64)>,
    /// The TLS links ([`crate::relay`]; after the session, which uses them).
    relays: Option<crate::relay::Relays>,
    /// Messages the access control refused, per host and route (see [`crate::refusals`]).
    refusals: Option<crate::refusals::Refusals>,
    /// The revoked hosts this session's access control leaves out.
    revoked: BTreeSet<String>,
    /// Watches the revocation list for a change.
    revocation_watch: Option<RevocationWatch>,
}

impl BridgeStage {
    /// summary.json `bridge.out`: each `out` route's key, policy and counts.
    fn out_summaries(&self) -> BTreeMap<String, OutRouteSummary> {
        self.outs
            .iter()
            .map(|o| {
                let route = OutRouteSummary {
                    key: key(&self.settings.namespace, &self.settings.robot, o.topic.service),
                    policy: format!("{:?}", o.policy).to_lowercase(),
                    counts: o.counts,
                };
                (o.topic.service.to_string(), route)
            })
            .collect()
    }

    /// summary.json `bridge.in`: each `in` route's counts, what the robot said it sent less what
    /// arrived (counted as dropped now, where no sequence gap showed it), and what the access
    /// control refused under its key. Returns them and the messages lost or refused in all.
    fn in_summaries(&self) -> (BTreeMap<String, InRouteSummary>, u64) {
        let wrong_robot = self.refusals.as_ref().map(|r| r.per_route()).unwrap_or_default();
        let mut lost_total = 0u64;
        let ins = self
            .ins
            .iter()
            .map(|r| {
                let c = r.counts;
                // What the other side said it sent, against what arrived here.
                // (What arrived of the sender's: refused signatures and lengths may be anyone's.)
                let arrived =
                    (c.received + c.queue_dropped + c.rate_dropped).saturating_sub(c.wrong_type + c.bad_length);
                let lost = self
                    .ends
                    .get(&r.from)
                    .and_then(|e| e.as_ref())
                    .and_then(|sent| sent.get(&r.service))
                    .map(|&sent| sent.saturating_sub(arrived));
                // What went missing without a sequence gap here (lost before the end) is counted now.
                let unseen = lost.unwrap_or(0).saturating_sub(c.seq_gaps);
                self.emitters[r.emitter].count_dropped("lost on the way", unseen);
                lost_total += lost.unwrap_or(0)
                    + c.wrong_type
                    + c.bad_length
                    + c.queue_dropped
                    + c.rate_dropped
                    + c.refused_non_finite
                    + c.refused_time
                    + c.refused_going_back;
                let route = InRouteSummary {
                    local: r.local.to_string(),
                    from: r.from.clone(),
                    service: r.service.clone(),
                    key: key(&self.settings.namespace, &r.from, &r.service),
                    counts: c,
                    lost_on_the_way: lost,
                    // Refused by the access control: sent under this route's key by a host that
                    // is not the robot (they never reach the counts above).
                    refused_wrong_robot: self
                        .refusals
                        .as_ref()
                        .map(|_| wrong_robot.get(&r.route_name).copied().unwrap_or(0)),
                };
                (r.route_name.clone(), route)
            })
            .collect();
        (ins, lost_total)
    }

    /// summary.json `bridge.security`: the mode and, with TLS, the links, refusals and limits.
    fn security_summary(&self) -> SecuritySummary {
        let links = self.relays.as_ref().map(crate::relay::Relays::counts);
        let refused = self.relays.as_ref().map(crate::relay::Relays::refused_total);
        match &self.settings.zenoh.tls {
            None => SecuritySummary { mode: "insecure".into(), tls: None },
            Some(t) => SecuritySummary {
                mode: "mutual_tls".into(),
                tls: Some(TlsSummary {
                    // Links refused by the TLS relays (no route: nothing got in).
                    refused_unauthenticated: refused,
                    links,
                    refused: self.refusals.as_ref().map(|r| r.summary()),
                    accept: AcceptSummary {
                        max_rate_hz: self.settings.accept.max_rate_hz,
                        queue_messages: self.settings.queue_messages,
                        queue_mib: self.settings.accept.queue_mib,
                        max_future_s: self.settings.accept.max_future_s,
                        max_age_s: self.settings.accept.max_age_s,
                    },
                    certificate: crate::read_certificate(&t.certificate).ok(),
                    receivers: t.receivers.clone(),
                    access_control: crate::access_control(&self.settings, &self.revoked),
                    revoked: self.revoked.clone(),
                    revocation_list: t.revocation_list(),
                }),
            },
        }
    }

    /// Waits (up to `wait_for_remote_s`) until every reliable route has a subscriber on the
    /// other side, saying what it waits for every 2 s.
    fn wait_for_remote(&self) {
        let limit = Duration::from_secs_f64(self.settings.wait_for_remote_s);
        if limit.is_zero() {
            return;
        }
        let t0 = Instant::now();
        let mut last_note = t0;
        loop {
            let waiting: Vec<&str> = self
                .outs
                .iter()
                .filter(|o| o.policy == Policy::Reliable)
                .filter(|o| !o.publisher.matching_status().wait().is_ok_and(|m| m.matching()))
                .map(|o| o.topic.service)
                .collect();
            if waiting.is_empty() {
                if t0.elapsed() > Duration::from_millis(500) {
                    tracing::info!(waited_s = t0.elapsed().as_secs_f64(), "the other side subscribed");
                }
                return;
            }
            if t0.elapsed() >= limit {
                tracing::warn!(
                    ?waiting,
                    "no subscriber on the other side after {:.0} s (wait_for_remote_s): sending anyway; what \
                     is sent before one subscribes is lost",
                    limit.as_secs_f64()
                );
                return;
            }
            if last_note.elapsed() >= Duration::from_secs(2) {
                tracing::info!(?waiting, "waiting for a subscriber on the other side");
                last_note = Instant::now();
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Takes every queued local message of every `out` route and hands it to Zenoh.
    fn pump_out(&mut self, rt: &mut Runtime) -> Result<usize, StageError> {
        let mut total = 0;
        // A reliable send may wait for the link: the heartbeat goes on meanwhile.
        let _hold = self.outs.iter().any(|o| o.policy == Policy::Reliable).then(|| rt.hold_heartbeat());
        for o in &mut self.outs {
            let OutRoute {
                tap,
                publisher,
                min_interval,
                next_send,
                signature,
                counts,
                last_seq,
                warned,
                topic,
                matched,
                buffers,
                ..
            } = o;
            total += tap.drain(&mut |r| {
                counts.received += 1;
                if let Some(last) = last_seq.insert(r.publisher, r.msg.seq)
                    && r.msg.seq > last + 1
                {
                    counts.missed_locally += r.msg.seq - last - 1;
                    tap.count_dropped("missed: sequence gap", r.msg.seq - last - 1);
                }
                if let Some(dt) = *min_interval {
                    let now = Instant::now();
                    if next_send.is_some_and(|t| now < t) {
                        counts.rate_dropped += 1;
                        tap.count_dropped("over the route's max_rate_hz", 1);
                        return ControlFlow::Continue(());
                    }
                    *next_send = Some(now + dt);
                }
                let data = buffers.payload(&[r.header, r.payload]);
                if !matched.load(Ordering::Relaxed) {
                    counts.no_subscriber += 1;
                    tap.count_dropped("no subscriber on the other side", 1);
                }
                match publisher.put(data).attachment(signature.clone()).wait() {
                    Ok(()) => {
                        counts.sent += 1;
                        // After the put: off the message's path.
                        counts.digest = fold(counts.digest, &[r.header, r.payload]);
                    }
                    Err(e) => {
                        counts.send_errors += 1;
                        tap.count_dropped("zenoh refused it", 1);
                        if !*warned {
                            tracing::warn!(
                                service = topic.service,
                                "not sent (counted in summary.json bridge.out): {e}"
                            );
                            *warned = true;
                        }
                    }
                }
                ControlFlow::Continue(())
            })?;
        }
        Ok(total)
    }

    /// Publishes what the Zenoh callbacks queued; acknowledges end markers.
    fn pump_in(&mut self, rt: &mut Runtime) -> Result<usize, StageError> {
        // Publishing may wait for a full local subscriber (when_full = wait), holding the link.
        let _hold = rt.hold_heartbeat();
        let mut n = 0;
        // Messages of routes that never wait first, then those that may wait for a full local
        // subscriber, then the ends of stream: a cloud waiting for the mapper must not hold back
        // the poses the mapper waits for (each route keeps its own order).
        let (mut quick, mut waiting, mut ends) = (vec![], vec![], vec![]);
        let taken = self.inbox.take();
        // The drops counted after the take: every message dropped before one taken is in them
        // (its gap in the sequence numbers is explained by them).
        self.count_inbox_drops();
        for item in taken {
            match &item {
                Incoming::Data { route, .. } if self.ins[*route].may_wait => waiting.push(item),
                Incoming::Data { .. } => quick.push(item),
                Incoming::End { .. } => ends.push(item),
            }
        }
        for item in quick.into_iter().chain(waiting).chain(ends) {
            match item {
                Incoming::Data { route, payload, attachment } => {
                    n += 1;
                    self.publish_in(route, &payload, attachment.as_ref())?;
                }
                Incoming::End { from, body } => self.on_end(from, &body),
            }
        }
        Ok(n)
    }

    /// Counts what the inbox dropped (receive queue full, over a route's rate) since the last time.
    fn count_inbox_drops(&mut self) {
        for r in &mut self.ins {
            let total = r.queue_dropped_before + self.inbox.dropped[r.index].load(Ordering::Relaxed);
            if total > r.counts.queue_dropped {
                self.emitters[r.emitter].count_dropped("receive queue full", total - r.counts.queue_dropped);
                r.drop_credit += total - r.counts.queue_dropped;
                r.counts.queue_dropped = total;
            }
            let total = r.rate_dropped_before + self.inbox.rate_dropped[r.index].load(Ordering::Relaxed);
            if total > r.counts.rate_dropped {
                let n = total - r.counts.rate_dropped;
                self.emitters[r.emitter].count_dropped("over the route's rate limit (accept.max_rate_hz)", n);
                r.counts.rate_dropped = total;
                r.drop_credit += n;
                if r.warned_refusals.insert("rate") {
                    tracing::warn!(from = %r.from, route = %r.route_name,
                        "messages dropped on arrival: over the route's rate limit (accept.max_rate_hz; counted in \
                         summary.json bridge.in as rate_dropped)");
                }
            }
        }
    }

    /// Checks one message of `in` route `route` (its wire signature, its length, its header's
    /// stamps and sequence, no NaN) and publishes it locally, counting what is refused.
    fn publish_in(
        &mut self,
        route: usize,
        payload: &zenoh::bytes::ZBytes,
        attachment: Option<&zenoh::bytes::ZBytes>,
    ) -> Result<(), StageError> {
        let r = &mut self.ins[route];
        r.counts.received += 1;
        let attachment = attachment.as_ref().map(|a| a.to_bytes());
        if attachment.as_deref() != Some(&r.signature[..]) {
            r.counts.wrong_type += 1;
            self.emitters[r.emitter].count_dropped("another wire signature", 1);
            if !r.warned {
                tracing::warn!(
                    from = %r.from,
                    service = %r.service,
                    expected = %String::from_utf8_lossy(&r.signature),
                    got = %attachment.as_deref().map(String::from_utf8_lossy).unwrap_or_default(),
                    "refused a message with another wire signature (counted in summary.json bridge.in)"
                );
                r.warned = true;
            }
            return Ok(());
        }
        // Zenoh's pieces as they are (a large message arrives as the fragments' buffers):
        // the only copy is each piece into the loaned sample.
        let parts: Vec<&[u8]> = payload.slices().collect();
        let len = payload.len();
        let head = gather_head(&parts);
        if let Err(e) = r.topic.check_len(len) {
            r.counts.bad_length += 1;
            self.emitters[r.emitter].count_dropped("not a message of the service's types", 1);
            if !r.warned {
                tracing::warn!(from = %r.from, service = %r.service, "refused a message: {e} (counted)");
                r.warned = true;
            }
            return Ok(());
        }
        let origin = match &r.clock {
            None => Some(Origin::Keep),
            Some(c) => lock(c).origin(),
        };
        let Some(h) = shared_types::MsgHeader::from_bytes(&head) else { return Ok(()) };
        match r.admit(&h, origin, &self.settings.accept) {
            Ok(0) => {}
            Ok(gap) => self.emitters[r.emitter].count_dropped("lost on the way", gap),
            Err(reason) => {
                self.emitters[r.emitter].count_dropped(reason, 1);
                return Ok(());
            }
        }
        if origin.is_none() {
            r.counts.origin_unaligned += 1;
            if !r.warned_clock {
                tracing::warn!(from = %r.from, service = %r.service,
                    "the clock of the sending robot's machine is not measured yet: origin_ns stays on its \
                     clock (counted in summary.json bridge.in as origin_unaligned)");
                r.warned_clock = true;
            }
        }
        let (reached, registered) =
            match self.emitters[r.emitter].send_parts_finite(&parts, origin.unwrap_or(Origin::Keep))? {
                Ok(sent) => sent,
                Err(rejection) => {
                    r.counts.refused_non_finite += 1;
                    r.warn_refusal("non_finite", &rejection.detail);
                    self.emitters[r.emitter].count_dropped("refused: a NaN or an infinity", 1);
                    return Ok(());
                }
            };
        r.counts.published += 1;
        r.counts.digest = fold(r.counts.digest, &parts);
        self.published += 1;
        if reached < registered {
            r.counts.undelivered += (registered - reached) as u64;
        }
        Ok(())
    }

    /// The end of stream of robot `from`, with what it says it sent: acknowledged.
    fn on_end(&mut self, from: String, body: &[u8]) {
        let sent: BTreeMap<String, u64> = serde_json::from_slice::<serde_json::Value>(body)
            .ok()
            .and_then(|v| serde_json::from_value(v["sent"].clone()).ok())
            .unwrap_or_default();
        tracing::info!(%from, ?sent, "end of stream from the other side");
        if let Err(e) = self.session.put(ack_key(&self.settings.namespace, &from), "ack").wait() {
            tracing::warn!(%from, "end marker not acknowledged: {e}");
        }
        self.ends.insert(from, Some(sent));
    }

    /// Messages handled and ends received so far: the kept counts are renewed when it moves.
    fn activity(&self) -> u64 {
        let outs: u64 = self.outs.iter().map(|o| o.counts.received).sum();
        let ins: u64 = self.ins.iter().map(|r| r.counts.received).sum();
        outs + ins + self.ends.values().filter(|e| e.is_some()).count() as u64
    }

    /// Snapshots the counts for a restarted instance (at most every [`KEEP_EVERY`], when they moved).
    fn keep_counts(&mut self, rt: &mut Runtime) {
        let activity = self.activity();
        if self.kept_at.is_some_and(|(t, a)| a == activity || t.elapsed() < KEEP_EVERY) {
            return;
        }
        self.kept_at = Some((Instant::now(), activity));
        let kept = Kept {
            out: self
                .outs
                .iter()
                .map(|o| {
                    let last_seq = o.last_seq.iter().map(|(p, s)| (p.to_string(), *s)).collect();
                    (o.topic.service.to_string(), KeptOut { counts: o.counts, last_seq })
                })
                .collect(),
            inbound: self
                .ins
                .iter()
                .map(|r| (r.route_name.clone(), KeptIn { counts: r.counts, last_seq: r.order.last_seq }))
                .collect(),
            ends: self.ends.clone(),
            published: self.published,
        };
        let written = serde_json::to_vec(&kept)
            .map_err(|e| e.to_string())
            .and_then(|b| rt.state().snapshot(KEPT, &b).map_err(|e| e.to_string()));
        if let Err(e) = written {
            tracing::warn!("counts not kept for a restart: {e}");
        }
    }

    fn ins_done(&self) -> bool {
        self.ends.values().all(Option::is_some) && self.inbox.is_empty()
    }

    /// Sends the end marker with the counts sent per service and waits for an acknowledgement.
    fn send_end(&mut self, rt: &mut Runtime) {
        if self.outs.is_empty() {
            return;
        }
        let sent: BTreeMap<&str, u64> = self.outs.iter().map(|o| (o.topic.service, o.counts.sent)).collect();
        let body = serde_json::json!({ "sent": sent }).to_string();
        let k = end_key(&self.settings.namespace, &self.settings.robot);
        if let Err(e) = self.session.put(&k, body).congestion_control(CongestionControl::Block).wait() {
            tracing::warn!("end marker not sent: {e}");
            self.end_acknowledged = Some(false);
            return;
        }
        let limit = Duration::from_secs_f64(self.settings.end_ack_timeout_s);
        let t0 = Instant::now();
        while !self.acked.load(Ordering::Relaxed) && t0.elapsed() < limit {
            rt.keep_alive();
            std::thread::sleep(Duration::from_millis(10));
        }
        let acked = self.acked.load(Ordering::Relaxed);
        if !acked && !limit.is_zero() {
            tracing::warn!(
                "no bridge acknowledged the end of stream within {:.1} s (end_ack_timeout_s): the other side \
                 may not have got everything",
                limit.as_secs_f64()
            );
        }
        self.end_acknowledged = Some(acked);
    }
}

impl Stage for BridgeStage {
    type Settings = BridgeSettings;

    fn open(_ctx: &ProcessContext, settings: BridgeSettings, rt: &mut Runtime) -> Result<Self, StageError> {
        // The revocation list as it is now; watched from here on (a change restarts the bridge).
        let (revoked, revocation_watch) = revocation_state(&settings)?;
        // Watched from before the session opens.
        let refusals = watch_refusals(&settings);
        let (session, relays) = open_session(&settings, &revoked)?;
        if let (Some(r), Some(relays)) = (&refusals, &relays) {
            r.names_from(relays.names());
        }
        log_session(&settings, &session);
        let outs = open_out_routes(&settings, &session, rt)?;
        let inbox = new_inbox(&settings, rt)?;
        // The clock of every robot received from (see crate::clock).
        let mut clocks = BTreeMap::new();
        if settings.clock != ClockMode::Keep {
            for from in settings.inbound.iter().map(|r| &r.from).collect::<BTreeSet<_>>() {
                let probe = ClockProbe::start(&session, &settings.namespace, from.clone(), settings.clock)?;
                clocks.insert(from.clone(), probe);
            }
        }
        let clock_answers = if outs.is_empty() { None } else { Some(answer_clock_asks(&settings, &session)?) };
        let (ins, emitters) = open_in_routes(&settings, &session, rt, &inbox, &clocks)?;
        let robots: BTreeSet<String> = settings.inbound.iter().map(|r| r.from.clone()).collect();
        let mut end_subscribers = vec![];
        for from in &robots {
            let k = end_key(&settings.namespace, from);
            let (inbox_cb, from_cb) = (inbox.clone(), from.clone());
            end_subscribers.push(
                session
                    .declare_subscriber(k.clone())
                    .callback(move |sample| {
                        inbox_cb.push_end(from_cb.clone(), sample.payload().to_bytes().into_owned());
                    })
                    .wait()
                    .map_err(|e| zenoh_err(format!("subscriber on {k}"), e))?,
            );
        }
        let acked = Arc::new(AtomicBool::new(false));
        let ack_subscriber = if outs.is_empty() {
            None
        } else {
            let k = ack_key(&settings.namespace, &settings.robot);
            let a = acked.clone();
            Some(
                session
                    .declare_subscriber(k.clone())
                    .callback(move |_| a.store(true, Ordering::Relaxed))
                    .wait()
                    .map_err(|e| zenoh_err(format!("subscriber on {k}"), e))?,
            )
        };
        let stage = Self {
            // A revoked robot's end of stream cannot come (nothing from it gets in): not waited for.
            ends: robots.into_iter().filter(|r| !revoked.contains(r)).map(|r| (r, None)).collect(),
            settings,
            session,
            outs,
            ins,
            emitters,
            inbox,
            _end_subscribers: end_subscribers,
            acked,
            _ack_subscriber: ack_subscriber,
            end_acknowledged: None,
            published: 0,
            started: Instant::now(),
            _clock_answers: clock_answers,
            clocks,
            kept_at: None,
            relays,
            refusals,
            revoked,
            revocation_watch,
        };
        stage.wait_for_remote();
        Ok(stage)
    }

    fn end_after(&self) -> EndAfter {
        if self.outs.is_empty() { EndAfter::Itself } else { EndAfter::from_list(&self.settings.end_after) }
    }

    fn step(&mut self, rt: &mut Runtime, _wake: Wake, inputs_ended: bool) -> Result<Step, StageError> {
        self.pump_out(rt)?;
        self.pump_in(rt)?;
        self.keep_counts(rt);
        if let Some(r) = &self.refusals {
            r.warn_new();
        }
        if let Some(new) = self.revocation_watch.as_ref().and_then(RevocationWatch::changed) {
            if crate::access_control(&self.settings, &new) == crate::access_control(&self.settings, &self.revoked) {
                // Nobody this bridge deals with: nothing to apply.
                tracing::info!(revoked = ?new, "the revocation list changed: this bridge's access control stays as it is");
                if let Some(gap) = crate::revocation_gap(&self.settings, &new) {
                    tracing::warn!("{gap}");
                }
                self.revoked = new;
            } else {
                // Zenoh's access control is fixed when the session opens: a new session applies
                // the list (this process exits and its restart opens it, counting on from the
                // kept counts).
                self.kept_at = None;
                self.keep_counts(rt);
                return Err(StageError::msg(format!(
                    "the revocation list changed (now revoked: {:?}, before: {:?}): restarting to apply it",
                    new, self.revoked
                )));
            }
        }
        let ins_done = self.ins_done();
        if self.outs.is_empty() {
            return Ok(if ins_done { Step::Done } else { Step::Idle });
        }
        Ok(if inputs_ended && !ins_done { Step::Pending } else { Step::Idle })
    }

    type Summary = BridgePart;

    fn finish(&mut self, rt: &mut Runtime, ending: Ending) -> Result<Self::Summary, StageError> {
        if ending == Ending::Stopped {
            if let Err(e) = self.pump_out(rt) {
                tracing::warn!("last drain: {e:#}");
            }
            if let Err(e) = self.pump_in(rt) {
                tracing::warn!("last publish: {e:#}");
            }
        }
        if ending == Ending::EndOfStream {
            self.send_end(rt);
        }
        let outs = self.out_summaries();
        if let Some(r) = &self.refusals {
            r.warn_new();
        }
        let (ins, lost_total) = self.in_summaries();
        let out_dropped: u64 = self.outs.iter().map(|o| o.counts.rate_dropped + o.counts.send_errors).sum();
        if lost_total > 0 || out_dropped > 0 {
            tracing::warn!(
                received_side_lost = lost_total,
                send_side_dropped = out_dropped,
                "messages lost or refused across the bridge (per route and reason in summary.json bridge)"
            );
        }
        for (robot, probe) in &self.clocks {
            let c = lock(&probe.state);
            if c.answered == 0 {
                tracing::warn!(%robot, asked = c.asked,
                    "the robot's bridge never answered a clock ask: origin_ns of what came from it stayed on its clock");
            }
        }
        let missing_ends: Vec<&String> = self.ends.iter().filter(|(_, e)| e.is_none()).map(|(r, _)| r).collect();
        if !missing_ends.is_empty() {
            tracing::warn!(?missing_ends, "no end of stream came from these robots");
        }
        if let Some(n) = self.relays.as_ref().map(crate::relay::Relays::refused_total).filter(|&n| n > 0) {
            tracing::warn!(
                refused_unauthenticated = n,
                "TLS links refused (no certificate, another CA's, an expired or revoked one, not TLS, or a Zenoh id \
                 that is not the certificate's): per peer and reason in summary.json bridge.security.links"
            );
        }
        let security = self.security_summary();
        Ok(BridgePart {
            bridge: BridgeSummary {
                security,
                namespace: self.settings.namespace.clone(),
                robot: self.settings.robot.clone(),
                zid: self.session.zid().to_string(),
                out: outs,
                inbound: ins,
                ends_received: self.ends.iter().filter(|(_, e)| e.is_some()).map(|(r, _)| r.clone()).collect(),
                ends_missing: missing_ends.into_iter().cloned().collect(),
                end_acknowledged: self.end_acknowledged,
                clock: self.clocks.iter().map(|(r, p)| (r.clone(), lock(&p.state).summary())).collect(),
                wall_s: self.started.elapsed().as_secs_f64(),
            },
        })
    }

    fn end_of_stream(&self) -> (u64, u64) {
        (self.published.saturating_sub(1), self.published)
    }

    /// A restarted bridge goes on counting from the killed instance's last kept counts (what it
    /// handled after them, at most 0.1 s, is not in them: on the receiving side it shows as lost).
    fn restore(&mut self, restart: Restart) -> Result<usize, StageError> {
        let Some(bytes) = restart.read_snapshot(KEPT)? else { return Ok(0) };
        let kept: Kept = match serde_json::from_slice(&bytes) {
            Ok(k) => k,
            Err(e) => {
                tracing::warn!("restarted: the killed instance's counts are unreadable ({e}): counting from 0");
                return Ok(0);
            }
        };
        for o in &mut self.outs {
            if let Some(k) = kept.out.get(o.topic.service) {
                o.counts = k.counts;
                o.last_seq = k.last_seq.iter().filter_map(|(p, s)| Some((p.parse().ok()?, *s))).collect();
            }
        }
        for r in &mut self.ins {
            if let Some(k) = kept.inbound.get(&r.route_name) {
                r.counts = k.counts;
                r.order = Order { last_seq: k.last_seq };
                // This instance's receive queue and rate limit count their drops from 0.
                r.queue_dropped_before = k.counts.queue_dropped;
                r.rate_dropped_before = k.counts.rate_dropped;
            }
        }
        for (robot, end) in kept.ends {
            if let Some(slot) = self.ends.get_mut(&robot)
                && end.is_some()
            {
                *slot = end;
            }
        }
        self.published = kept.published;
        tracing::info!(
            sent = self.outs.iter().map(|o| o.counts.sent).sum::<u64>(),
            published = self.published,
            "restarted: counting on from the killed instance's counts"
        );
        Ok(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::buffers::SendBuffers;

    #[test]
    fn the_head_of_a_message_in_pieces_is_its_first_32_bytes() {
        let data: Vec<u8> = (0..40u8).collect();
        let mut expected = [0u8; 32];
        expected.copy_from_slice(&data[..32]);
        assert_eq!(gather_head(&[&data]), expected);
        assert_eq!(gather_head(&[&data[..3], &[], &data[3..31], &data[31..]]), expected);
        let mut short = [0u8; 32];
        short[..10].copy_from_slice(&data[..10]);
        assert_eq!(gather_head(&[&data[..4], &data[4..10]]), short);
    }

    fn header(seq: u64, stamp_ns: u64, origin_ns: u64) -> shared_types::MsgHeader {
        shared_types::MsgHeader { seq, stamp_ns, origin_ns, publish_ns: 0 }
    }

    #[test]
    fn sequence_numbers_must_go_forward_but_a_restart_is_accepted() {
        let (a, now) = (crate::Accept::default(), 1_000_000_000_000);
        let mut o = Order::default();
        let ok = |gap, restarted| Verdict::Accepted { gap, restarted };
        assert_eq!(o.admit(&header(100, 10, now), Some(Origin::Keep), &a, now), ok(0, false));
        assert_eq!(o.admit(&header(101, 11, now), Some(Origin::Keep), &a, now), ok(0, false));
        assert_eq!(o.admit(&header(104, 11, now), Some(Origin::Keep), &a, now), ok(2, false), "a gap of 2");
        assert!(matches!(o.admit(&header(104, 12, now), None, &a, now), Verdict::GoingBack(_)), "a repeat");
        assert!(matches!(o.admit(&header(90, 12, now), None, &a, now), Verdict::GoingBack(_)), "a replay");
        // Stamps may go back (a service re-publishing a past segment).
        assert_eq!(o.admit(&header(105, 5, now), None, &a, now), ok(0, false));
        // Refused for its time, its number still counts: no gap after it.
        assert!(matches!(o.admit(&header(106, 6, now + 10 * now), Some(Origin::Keep), &a, now), Verdict::OutOfTime(_)));
        assert_eq!(o.admit(&header(107, 7, now), Some(Origin::Keep), &a, now), ok(0, false));
        // The publisher restarted: its numbers start again.
        assert_eq!(o.admit(&header(0, 1, now), None, &a, now), ok(0, true));
        assert_eq!(o.admit(&header(1, 2, now), None, &a, now), ok(0, false));
    }

    #[test]
    fn origin_must_lie_in_the_accepted_window_once_on_this_clock() {
        let a = crate::Accept { max_future_s: 1.0, max_age_s: 120.0, ..Default::default() };
        let now = 1_000_000_000_000u64;
        let s = 1_000_000_000u64;
        let check = |origin_ns: u64, origin| {
            let mut o = Order::default();
            o.admit(&header(1, 1, origin_ns), origin, &a, now)
        };
        let ok = Verdict::Accepted { gap: 0, restarted: false };
        assert_eq!(check(now - 100 * s, Some(Origin::Keep)), ok);
        assert!(matches!(check(now - 121 * s, Some(Origin::Keep)), Verdict::OutOfTime(_)));
        assert!(matches!(check(now + 2 * s, Some(Origin::Keep)), Verdict::OutOfTime(_)));
        assert!(matches!(check(0, Some(Origin::Keep)), Verdict::OutOfTime(_)), "unset");
        // On another machine's clock: shifted onto this one first.
        assert_eq!(check(now + 500 * s, Some(Origin::Shift(-(500 * s as i64)))), ok);
        assert!(matches!(check(now, Some(Origin::Shift(10 * s as i64))), Verdict::OutOfTime(_)));
        // The offset not known yet: not checked.
        assert_eq!(check(now + 500 * s, None), ok);
    }

    #[test]
    fn a_token_bucket_lets_one_seconds_worth_through_then_the_rate() {
        let mut b = Bucket::new(10.0);
        let t0 = b.last;
        assert_eq!((0..15).filter(|_| b.take(t0)).count(), 10);
        assert!(!b.take(t0 + Duration::from_millis(50)));
        assert!(b.take(t0 + Duration::from_millis(160)));
        let mut slow = Bucket::new(0.5);
        assert!(slow.take(t0));
        assert!(!slow.take(t0 + Duration::from_secs(1)));
        assert!(slow.take(t0 + Duration::from_secs(3)));
    }

    #[test]
    fn send_buffers_hold_the_parts_in_order_and_are_reused() {
        let pool = SendBuffers::default();
        let z = pool.payload(&[b"head", b"", b"payload"]);
        assert_eq!(&*z.to_bytes(), b"headpayload");
        assert!(lock(&pool.0).is_empty());
        drop(z);
        let kept = lock(&pool.0).first().map(|b| b.capacity()).unwrap_or(0);
        assert!(kept >= 11, "the buffer went back to the pool");
        let again = pool.payload(&[b"x"]);
        assert_eq!(&*again.to_bytes(), b"x");
        assert!(lock(&pool.0).is_empty(), "the kept buffer was taken");
    }

    #[test]
    fn digest_folds_parts_as_one_message_and_depends_on_order() {
        // Long parts of odd lengths too (a cloud's header and its 12-byte points).
        let long: Vec<u8> = (0..100_003u32).map(|i| (i * 7 + i / 13) as u8).collect();
        let (h, p) = long.split_at(97);
        assert_eq!(fold(7, &[h, p]), fold(7, &[&long]));
        let (a, b) = (b"header".as_slice(), b"payload bytes".as_slice());
        let whole = [a, b].concat();
        assert_eq!(fold(DIGEST0, &[a, b]), fold(DIGEST0, &[&whole]));
        let ab = fold(fold(DIGEST0, &[a]), &[b]);
        let ba = fold(fold(DIGEST0, &[b]), &[a]);
        assert_ne!(ab, ba);
    }
}
