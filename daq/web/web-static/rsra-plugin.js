/* rsra plugin for NASA Open MCT: objects from the gateway's telemetry dictionary, history over
 * HTTP (/api/history), real-time points over one WebSocket (/ws), limits from the points'
 * "lim" field (computed by the gateway: noise budget, chi-square band of the NIS, node states,
 * flags, verdicts) and a default layout. Apache-2.0, part of rsra. */
(function () {
  'use strict';
  const NS = 'rsra';
  const TYPE = 'rsra.telemetry';
  const LIMITS = {
    yellow: { cssClass: 'is-limit--yellow', name: 'Yellow', low: -Infinity, high: Infinity },
    red: { cssClass: 'is-limit--red', name: 'Red', low: -Infinity, high: Infinity }
  };

  // counters of what reached the views (read by the browser test and handy in the console)
  // gaps: breaks put into history answers, liveGaps: into real-time points (per series)
  window.rsraStats = { delivered: {}, history: {}, gaps: {}, liveGaps: {}, messages: 0 };

  // A gap in a plotted series (a stopped or restarted service): a point with no value between
  // the two points around it, which the plot does not join (Open MCT keeps one invalid value
  // between valid ones; its WebGL line leaves out the segments to it). The measurement's
  // gap_ms (dictionary) is the longest time the line still joins; a thinned history answer
  // joins up to 3 times its median spacing, whichever is longer.
  function gapPoint(key, a, b, live) {
    const st = live ? window.rsraStats.liveGaps : window.rsraStats.gaps;
    st[key] = (st[key] || 0) + 1;
    return { utc: (a.utc + b.utc) / 2, value: NaN, gap: true };
  }
  function withGaps(key, data, gapMs) {
    if (!gapMs || data.length < 2) {
      return data;
    }
    const dt = [];
    for (let i = 1; i < data.length; i++) {
      dt.push(data[i].utc - data[i - 1].utc);
    }
    const median = dt.slice().sort((a, b) => a - b)[dt.length >> 1];
    const limit = Math.max(gapMs, 3 * median);
    const out = [data[0]];
    for (let i = 1; i < data.length; i++) {
      if (dt[i - 1] > limit) {
        out.push(gapPoint(key, data[i - 1], data[i]));
      }
      out.push(data[i]);
    }
    return out;
  }

  // Without WebGL Open MCT draws plots on a 2D canvas, whose lineTo ignores a NaN point
  // (HTML spec) and so joins the line across a gap: there a lineTo after one with NaN starts
  // a new piece of line (moveTo). Only calls the spec makes no-ops change meaning.
  (function () {
    const proto = window.CanvasRenderingContext2D && window.CanvasRenderingContext2D.prototype;
    if (!proto || proto.rsraGaps) {
      return;
    }
    const lineTo = proto.lineTo;
    const moveTo = proto.moveTo;
    const beginPath = proto.beginPath;
    const lifted = new WeakSet();
    proto.lineTo = function (x, y) {
      if (Number.isNaN(x) || Number.isNaN(y)) {
        lifted.add(this);
        return undefined;
      }
      if (lifted.has(this)) {
        lifted.delete(this);
        return moveTo.call(this, x, y);
      }
      return lineTo.call(this, x, y);
    };
    proto.beginPath = function () {
      lifted.delete(this);
      return beginPath.call(this);
    };
    proto.rsraGaps = true;
  })();

  function id(key) {
    return { namespace: NS, key: key };
  }

  // values shown in thousands (kN, kN·m; the points stay SI): short tick numbers
  const KILO = { key: 'rsra.kilo', parse: (v) => Number(v), validate: () => true,
    format: (v) => (typeof v === 'number' && Number.isFinite(v)
      ? String(Number((v / 1000).toPrecision(4))) : String(v)) };

  function valueMeta(m) {
    const fmt = m.kilo ? { format: KILO.key }
      : m.format === 'string' ? { format: 'string' }
        : m.format === 'integer' ? { formatString: '%d' }
          : { formatString: '%0.' + (m.decimals === undefined ? 1 : m.decimals) + 'f' };
    const values = [
      { key: 'utc', source: 'utc', name: 'Time', format: 'utc', hints: { domain: 1 } },
      Object.assign({ key: 'value', name: m.value_name || m.name,
        unit: m.kilo ? 'k' + m.unit : m.unit, hints: { range: 1 } }, fmt)
    ];
    (m.extra || []).forEach(function (e, i) {
      values.push({ key: e.key, name: e.name, unit: e.unit,
        format: ['detail', 'mode', 'content'].includes(e.key) ? 'string' : undefined,
        formatString: ['detail', 'mode', 'content'].includes(e.key) ? undefined : '%0.3f',
        hints: { range: i + 2 } });
    });
    return values;
  }

  function series(key, color, limitLines) {
    return { identifier: id(key), color: color, markers: false, alarmMarkers: true,
      limitLines: Boolean(limitLines) };
  }

  // a plot's y axis: a short label of its own (the default, the first series' name, ran
  // into the tick numbers), log scale where asked
  function yAxis(label, log) {
    return { label: label, logMode: Boolean(log), autoscale: true, autoscalePadding: 0.1 };
  }

  function buildObjects(dic) {
    const objs = {};
    const groups = {};
    dic.measurements.forEach(function (m) {
      objs[m.id] = {
        identifier: id(m.id), name: m.name, type: TYPE, location: NS + ':folder.' + m.group,
        telemetry: { values: valueMeta(m) }, rsra: m
      };
      (groups[m.group] = groups[m.group] || []).push(id(m.id));
    });
    const axes = ['X', 'Y', 'Z', 'L', 'M', 'N'];
    const hubPlots = axes.map(function (ax) {
      const key = 'plot.hub.' + ax;
      const unit = 'k' + dic.measurements.find((m) => m.id === 'hub.H.' + ax).unit;
      objs[key] = {
        identifier: id(key), type: 'telemetry.plot.overlay', location: NS + ':plot.hub',
        name: ax + ' (' + unit + ')',
        composition: ['hub.lower.', 'hub.upper.', 'hub.static.', 'hub.H.'].map((p) => id(p + ax)),
        configuration: { series: [
          series('hub.lower.' + ax, '#e0b800'), series('hub.upper.' + ax, '#e0b800'),
          series('hub.static.' + ax, '#6f7f8f'), series('hub.H.' + ax, '#35c7ff')
        ], yAxis: yAxis(ax + ' ' + unit) }
      };
      return id(key);
    });
    const layoutParts = {
      'plot.hub': { type: 'telemetry.plot.stacked', name: 'Hub loads (' + dic.frame
        + ' axes): filter H (blue), static (grey), H ± ' + dic.z_yellow.toFixed(2)
        + 'σ static noise bound (yellow)',
        composition: hubPlots },
      // log scale: the NIS spans 1 to thousands (a faulted sample), its χ² band 0.5 to 27
      'plot.nis': { type: 'telemetry.plot.overlay',
        name: 'NIS against its χ² band (6 dof, log scale)', composition: [id('nis')],
        configuration: { series: [series('nis', '#35c7ff', true)], yAxis: yAxis('NIS', true) } },
      'lad.nodes': { type: 'LadTable', name: 'Nodes and health',
        composition: dic.nodes.map((n) => id('node.' + n))
          .concat([id('hub.flags'), id('hub.omega')])
          .concat(dic.measurements.filter((m) => m.group === 'Health').map((m) => id(m.id))),
        configuration: { hiddenColumns: { timestamp: true, type: true }, isFixedLayout: false } },
      // with its time: the angles' below are this run's
      'lad.ident': { type: 'LadTable', name: 'Latest identification',
        composition: [id('ident.verdict'), id('ident.determined'), id('ident.advice')],
        configuration: { hiddenColumns: { type: true }, isFixedLayout: false } },
      'table.angles': { type: 'table', name: 'Load-cell angles (deg) and their σ',
        composition: dic.angles.map((n) => id('angle.' + n)),
        // name, angle, σ: every unit deg, said in the name; the ∓1σ bounds stay in the
        // telemetry for plots. The time is the identification's, whole in the table above
        // (Open MCT splits a table's width evenly: a time column was cut at 1600 px)
        configuration: { hiddenColumns: { utc: true, 'value-unit': true, 'sigma-unit': true,
          lo: true, 'lo-unit': true, hi: true, 'hi-unit': true }, rowLimit: dic.angles.length } }
    };
    Object.keys(layoutParts).forEach(function (k) {
      objs[k] = Object.assign({ identifier: id(k), location: NS + ':layout' }, layoutParts[k]);
    });
    // a flexible layout (sizes in % of the page, not pixels: every part fits the width the
    // browser gives it); three columns, so that the hub loads, every node and health counter,
    // the identification and all 14 angles with their time are on screen without scrolling
    // from 1600×1000 (the browse tree and the inspector start hidden: index.html)
    function frame(key, size) {
      return { id: 'rsra-' + key, domainObjectIdentifier: id(key), size: size, noFrame: false };
    }
    objs.layout = {
      identifier: id('layout'), type: 'flexible-layout', location: NS + ':root',
      name: 'Rig ' + dic.rig + ' — ' + (dic.source || 'default layout'),
      composition: Object.keys(layoutParts).map(id),
      configuration: {
        rowsLayout: false,
        containers: [
          { id: 'rsra-left', size: 41, frames: [frame('plot.hub', 100)] },
          { id: 'rsra-middle', size: 24, frames: [frame('lad.nodes', 100)] },
          { id: 'rsra-right', size: 35, frames: [frame('lad.ident', 17),
            frame('table.angles', 45), frame('plot.nis', 38)] }
        ]
      }
    };
    const folders = Object.keys(groups).map(function (g) {
      objs['folder.' + g] = { identifier: id('folder.' + g), type: 'folder', name: g,
        location: NS + ':root', composition: groups[g] };
      return id('folder.' + g);
    });
    objs.root = { identifier: id('root'), type: 'folder', location: 'ROOT',
      name: 'rsra ' + dic.rig + ' (' + dic.prefix + ')',
      composition: [id('layout')].concat(folders) };
    Object.values(objs).forEach(function (o) {
      o.configuration = o.configuration || {}; // views keep their settings there
    });
    return objs;
  }

  function Realtime(url) {
    this.url = url;
    this.listeners = {};
    this.open();
  }
  Realtime.prototype.open = function () {
    const self = this;
    this.ws = new WebSocket(this.url);
    this.ws.onopen = function () {
      const ids = Object.keys(self.listeners);
      if (ids.length) {
        self.ws.send(JSON.stringify({ subscribe: ids }));
      }
    };
    this.ws.onmessage = function (ev) {
      const msg = JSON.parse(ev.data);
      const st = window.rsraStats;
      st.messages += 1;
      (msg.points || []).forEach(function (p) {
        const l = self.listeners[p[0]] || [];
        if (l.length) {
          st.delivered[p[0]] = (st.delivered[p[0]] || 0) + 1;
        }
        l.forEach((cb) => cb(p[1]));
      });
    };
    this.ws.onclose = function () {
      setTimeout(() => self.open(), 1000);
    };
  };
  Realtime.prototype.send = function (msg) {
    if (this.ws.readyState === WebSocket.OPEN) {
      this.ws.send(JSON.stringify(msg));
    }
  };
  Realtime.prototype.subscribe = function (key, cb) {
    const l = (this.listeners[key] = this.listeners[key] || []);
    l.push(cb);
    if (l.length === 1) {
      this.send({ subscribe: [key] });
    }
    const self = this;
    return function () {
      const i = l.indexOf(cb);
      if (i >= 0) {
        l.splice(i, 1);
      }
      if (!l.length) {
        delete self.listeners[key];
        self.send({ unsubscribe: [key] });
      }
    };
  };

  window.RsraPlugin = function (dic) {
    return function install(openmct) {
      const objs = buildObjects(dic);
      openmct.telemetry.addFormat(KILO);
      openmct.types.addType(TYPE, { name: 'rsra telemetry', cssClass: 'icon-telemetry',
        description: 'A series of the rsra rig telemetry', creatable: false });
      openmct.objects.addRoot(id('root'));
      openmct.objects.addProvider(NS, {
        get: function (identifier) {
          const o = objs[identifier.key];
          return o ? Promise.resolve(JSON.parse(JSON.stringify(o)))
            : Promise.reject(new Error('no such rsra object ' + identifier.key));
        },
        // views (plots, tables) keep their settings on their object: in this page only
        create: function () {
          return Promise.resolve(false);
        },
        update: function (o) {
          objs[o.identifier.key] = JSON.parse(JSON.stringify(o));
          return Promise.resolve(true);
        }
      });
      const proto = location.protocol === 'https:' ? 'wss://' : 'ws://';
      const rt = new Realtime(proto + location.host + '/ws');
      openmct.telemetry.addProvider({
        supportsRequest: (o) => o.type === TYPE,
        request: function (o, options) {
          const q = new URLSearchParams({ id: o.identifier.key, start: options.start,
            end: options.end });
          if (options.strategy === 'latest') {
            q.set('strategy', 'latest');
          }
          // a gateway under load answers 503 with Retry-After: ask again (a few times)
          const ask = (tries) => fetch('/api/history?' + q.toString()).then(function (r) {
            if (r.status === 503 && tries > 0) {
              const s = Number(r.headers.get('Retry-After')) || 1;
              return new Promise((ok) => setTimeout(ok, 1000 * s)).then(() => ask(tries - 1));
            }
            return r.ok ? r.json() : [];
          });
          return ask(5).then(function (d) {
            const st = window.rsraStats.history;
            st[o.identifier.key] = (st[o.identifier.key] || 0) + d.length;
            return options.strategy === 'latest' ? d
              : withGaps(o.identifier.key, d, o.rsra && o.rsra.gap_ms);
          });
        },
        supportsSubscribe: (o) => o.type === TYPE,
        subscribe: function (o, cb) {
          const key = o.identifier.key;
          const gapMs = o.rsra && o.rsra.gap_ms;
          let last = null;
          return rt.subscribe(key, function (d) {
            if (gapMs && last !== null && d.utc - last.utc > gapMs) {
              cb(gapPoint(key, last, d, true));
            }
            last = d;
            cb(d);
          });
        },
        supportsLimits: (o) => o.type === TYPE,
        getLimitEvaluator: function () {
          return { evaluate: function (datum, valueMetadata) {
            if (valueMetadata && valueMetadata.key !== 'value') {
              return undefined;
            }
            return datum && datum.lim ? LIMITS[datum.lim] : undefined;
          } };
        },
        getLimits: function (o) {
          const lim = o.rsra && o.rsra.limits;
          return { limits: function () {
            if (!lim) {
              return Promise.resolve({});
            }
            return Promise.resolve({
              WARNING: { low: { color: 'yellow', value: lim.yellow[0] },
                high: { color: 'yellow', value: lim.yellow[1] } },
              CRITICAL: { low: { color: 'red', value: 0 }, high: { color: 'red', value: lim.red[1] } }
            });
          } };
        }
      });
    };
  };
})();
