#!/usr/bin/env python3
"""The session start's probation timeline, per session, from an `evermap-agent sessions` report.json
(issue 33): each match judged while a placement was on probation (agreed? past the placing cloud?
independent? counted? which submap?), each contest with each rival's z, each whole-map search made
while the placement misfit (where its answer lay, its z, why it did not replace the placement), each end, timed in seconds
after the session's start. By default only the matches that counted or disagreed; --all shows every one.

    python3 scripts/probation_timeline.py OUT_DIR/report.json [SESSION ...] [--all]
"""
import json, sys
args = [a for a in sys.argv[1:] if not a.startswith('--')]
show_all = '--all' in sys.argv
r = json.load(open(args[0]))
want = set(int(a) for a in args[1:])
scores = {s['session']: s for s in r['session_scores']}
for s in r['sessions']:
    k = s['session']
    if k == 0 or (want and k not in want):
        continue
    sc = scores.get(k, {})
    tl = s.get('probation_timeline', [])
    print(f"== session {k}: placed_after {sc.get('placed_after_s')} committed_after {sc.get('committed_after_s')} "
          f"committed_at_node {s.get('committed_at_node')} cross closures {s['cross_session_closures']} steps {len(tl)}")
    first_agree = first_counted = None
    n_m = n_agree = n_counted = n_notpast = n_notindep = 0
    for st in tl:
        t = st.get('time_s')
        ts = f"{t:7.1f}" if t is not None else '    -  '
        if st['step'] == 'match':
            n_m += 1
            n_agree += st['agrees']
            n_counted += st['counted'] and st['agrees']
            if st['agrees'] and not st['past_placement']: n_notpast += 1
            if st['agrees'] and st['past_placement'] and not st['independent']: n_notindep += 1
            if st['agrees'] and first_agree is None: first_agree = t
            if st['counted'] and st['agrees'] and first_counted is None: first_counted = t
            if show_all or st['counted'] or not st['agrees']:
                ov = st['placing_view_overlap']
                nc = st['nearest_counted_m']
                print(f"  {ts} match node {st['node']:5d} (at {st['at_node']:5d}) submap {st['submap']['trajectory']}/{st['submap']['index']:<3d} "
                      f"past {st['past_placing_m']:7.2f} m  dt {st['translation_m']:.2f}/{st['translation_tolerance_m']:.2f} "
                      f"dθ {st['rotation_rad']*57.3:.1f}/{st['rotation_tolerance_rad']*57.3:.1f}° "
                      f"{'AGREE' if st['agrees'] else 'DISAGREE'} past={int(st['past_placement'])} ov={'-' if ov is None else f'{ov:.2f}'} "
                      f"indep={int(st['independent'])} near={'-' if nc is None else f'{nc:.1f}'} "
                      f"{'COUNTED' if st['counted'] else '       '} a={st['agreeing']}/{st['agreeing_submaps']}sm d={st['disagreeing']}")
        elif st['step'] == 'contest':
            z = ', '.join('-' if v is None else f'{v:.2f}' for v in st['z'])
            pz = ', '.join('-' if v is None else f'{v:.2f}' for v in st.get('piece_z', []))
            pieces = f" pieces [{pz}]" if pz else ''
            print(f"  {ts} CONTEST node {st['node']} (at {st['at_node']}) route {st['route_nodes']} nodes: z [{z}]{pieces} vs {st['min_z']} -> {st['decision']}")
        elif st['step'] == 'second_opinion':
            off = st['answer_offset']
            where = '-' if off is None else f"({off[0]:.2f}, {off[1]:.2f}) m {off[2]:.1f}°"
            z = '-' if st['z'] is None else f"{st['z']:.2f}"
            print(f"  {ts} SECOND OPINION (at {st['at_node']}) route {st['route_nodes']} nodes: answer {where} z {z} -> {st['decision']}")
        else:
            print(f"  {ts} {st['step'].upper()} {dict((a,b) for a,b in st.items() if a not in ('step','time_s'))}")
    print(f"  matches {n_m}, agreeing {n_agree}, counted {n_counted}, agreeing-not-past {n_notpast}, agreeing-past-not-independent {n_notindep}; first agreeing at {first_agree}, first counted at {first_counted}")
