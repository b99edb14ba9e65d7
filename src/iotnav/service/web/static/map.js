// iotnav live map: the fleet's latest clean positions (live over /api/socket), a device's clean
// track beside its raw fixes for a period with its trips and stops (map and list, from
// /api/reports/trips|stops) and its events on a timeline (/api/reports/events, and live alerts
// from the socket; a click centres the map on one), geofences (circles placed, polygons drawn
// corner by corner and edited by dragging; moved and deleted), each position's uncertainty as a
// circle of its accuracy radius (metres, as the API gives it), clean and raw alike.
// Everything comes from the API with the bearer token; nothing is fetched from elsewhere except
// map tiles when the service was given a tile URL.
(function () {
  'use strict';

  var cfg = JSON.parse(document.getElementById('iotnav-config').textContent);
  var COLORS = ['#1f77b4', '#d62728', '#2ca02c', '#9467bd', '#8c564b', '#e377c2', '#17becf', '#bcbd22'];
  var CLEAN = '#1f5fbf', RAW = '#e8771a', FENCE = '#2a9d3a', STOP = '#7b3fa0', EVENT = '#d4148a';
  var M_PER_DEG = Math.PI / 180 * 6371008.8; // metres per degree of latitude (mean Earth radius)

  // What the page shows, readable from a console (and by the browser test).
  var state = {
    ready: false, socketOpen: false, engine: null, admin: null,
    devices: {}, latest: {}, track: null, report: null, selectedEvent: null, polygon: null,
    geofences: [], errors: []
  };
  window.iotnav = state;

  var $ = function (id) { return document.getElementById(id); };

  // Leaflet puts a string tooltip in as HTML; names come from devices (an OsmAnd id is any text),
  // so every tooltip gets a text node instead
  function text(s) {
    var span = document.createElement('span');
    span.textContent = s;
    return span;
  }

  function showError(msg) {
    state.errors.push(msg);
    $('error').textContent = msg;
  }

  // --- token: given once as /#token=..., kept for the tab's life ------------------------
  var m = /(?:^|[#&])token=([^&]+)/.exec(location.hash);
  if (m) {
    sessionStorage.setItem('iotnav-token', decodeURIComponent(m[1]));
    history.replaceState(null, '', location.pathname + location.search);
  }
  var token = sessionStorage.getItem('iotnav-token');

  function api(path, options) {
    var opts = options || {};
    opts.headers = Object.assign({ Authorization: 'Bearer ' + token }, opts.headers || {});
    return fetch(path, opts).then(function (r) {
      if (r.status === 401) {
        sessionStorage.removeItem('iotnav-token');
        $('login').hidden = false;
        throw new Error('the token was refused (401): give another');
      }
      if (!r.ok) {
        return r.text().then(function (t) { throw new Error(path.split('?')[0] + ': ' + r.status + ' ' + t); });
      }
      return r.status === 204 ? null : r.json();
    });
  }

  // --- map, tiles or the metric grid ------------------------------------------------------
  var map = L.map('map', { worldCopyJump: true }).setView([20, 0], 2);
  // state.moving: the view is changing (set before an animated move starts, which Leaflet
  // begins on the next animation frame; every move ends with 'moveend')
  map.on('movestart', function () { state.moving = true; });
  map.on('moveend', function () { state.moving = false; });
  function fit(bounds, maxZoom) {
    state.moving = true;
    map.fitBounds(bounds, { padding: [40, 40], maxZoom: maxZoom });
  }
  L.control.scale({ metric: true, imperial: false, maxWidth: 160 }).addTo(map);
  var gridLayer = L.layerGroup();
  var gridLabel = L.control({ position: 'bottomright' });
  gridLabel.onAdd = function () { var d = L.DomUtil.create('div', 'grid-label'); return d; };

  function niceStep(metres) {
    var p = Math.pow(10, Math.floor(Math.log10(metres)));
    var steps = [1, 2, 5, 10];
    for (var i = 0; i < steps.length; i++) { if (steps[i] * p >= metres) { return steps[i] * p; } }
    return 10 * p;
  }

  // Lines of constant latitude and longitude spaced by a round number of metres (at the view's
  // centre latitude, about 100 px apart); the scale bar gives the same scale.
  function drawGrid() {
    gridLayer.clearLayers();
    var size = map.getSize();
    var y = size.y / 2;
    var perHundredPx = map.distance(map.containerPointToLatLng([0, y]), map.containerPointToLatLng([100, y]));
    if (!(perHundredPx > 0)) { return; }
    var step = niceStep(perHundredPx);
    var degLat = step / M_PER_DEG;
    var b = map.getBounds();
    var degLon = degLat / Math.max(Math.cos(b.getCenter().lat * Math.PI / 180), 1e-6);
    var style = { color: '#c8c8c8', weight: 1, interactive: false };
    var s = Math.max(b.getSouth(), -85), n = Math.min(b.getNorth(), 85);
    var lat0 = Math.floor(s / degLat) * degLat, lon0 = Math.floor(b.getWest() / degLon) * degLon;
    var lines = 0;
    for (var lat = lat0; lat <= n + degLat && lines < 400; lat += degLat, lines++) {
      gridLayer.addLayer(L.polyline([[lat, b.getWest() - degLon], [lat, b.getEast() + degLon]], style));
    }
    for (var lon = lon0; lon <= b.getEast() + degLon && lines < 800; lon += degLon, lines++) {
      gridLayer.addLayer(L.polyline([[s - degLat, lon], [n + degLat, lon]], style));
    }
    var label = step >= 1000 ? (step / 1000) + ' km' : step + ' m';
    gridLabel.getContainer().textContent = 'grid ' + label + ' (no map tiles)';
    state.gridStepM = step;
  }

  if (cfg.tileUrl) {
    L.tileLayer(cfg.tileUrl, { attribution: cfg.tileAttribution || '', maxZoom: 19 }).addTo(map);
  } else {
    gridLayer.addTo(map);
    gridLabel.addTo(map);
    map.on('moveend zoomend resize', drawGrid);
    drawGrid();
  }

  // one pane each, stacked: geofences, clean track, raw fixes above it (a person compares the
  // two), latest positions on top (Leaflet's overlay pane is at z-index 400)
  // (trip ends, stops, events and the polygon being edited above them all)
  ['fences', 'clean', 'raw', 'latest', 'marks'].forEach(function (name, i) {
    map.createPane(name).style.zIndex = String(390 + 10 * i);
  });
  var fenceLayer = L.featureGroup().addTo(map);
  var cleanLayer = L.featureGroup().addTo(map);
  var rawLayer = L.featureGroup().addTo(map);
  var latestLayer = L.featureGroup().addTo(map);
  var segLayer = L.featureGroup().addTo(map);
  var eventLayer = L.featureGroup().addTo(map);
  L.control.layers(null, {
    'Latest positions': latestLayer, 'Clean track': cleanLayer, 'Raw fixes': rawLayer,
    'Trips and stops': segLayer, Events: eventLayer, Geofences: fenceLayer
  }, { collapsed: false }).addTo(map);

  // --- devices and their latest clean position --------------------------------------------
  function color(id) { return COLORS[(id - 1) % COLORS.length]; }

  function fmtTime(iso) { return iso ? iso.replace('T', ' ').replace(/\.\d+Z$/, 'Z') : '-'; }

  function renderDevices() {
    var ul = $('devices');
    var sel = $('track-device');
    var chosen = sel.value;
    ul.textContent = '';
    sel.textContent = '';
    Object.keys(state.devices).map(Number).sort(function (a, b) { return a - b; }).forEach(function (id) {
      var d = state.devices[id], p = state.latest[id];
      var li = document.createElement('li');
      li.dataset.deviceId = id;
      if (state.track && state.track.deviceId === id) { li.className = 'selected'; }
      var sw = document.createElement('span');
      sw.className = 'swatch';
      sw.style.background = color(id);
      li.appendChild(sw);
      li.appendChild(document.createTextNode(d.name));
      var meta = document.createElement('div');
      meta.className = 'meta';
      meta.textContent = p ? fmtTime(p.fixTime) + ' · ±' + p.accuracy.toFixed(1) + ' m · ' +
        (p.speed * 0.514444).toFixed(1) + ' m/s' : 'no position yet';
      li.appendChild(meta);
      li.addEventListener('click', function () { sel.value = String(id); showTrack(id, null, null); });
      ul.appendChild(li);
      var opt = document.createElement('option');
      opt.value = String(id);
      opt.textContent = d.name;
      sel.appendChild(opt);
    });
    if (chosen) { sel.value = chosen; }
  }

  function placeLatest(p) {
    var old = state.latest[p.deviceId];
    if (old && old.fixTime > p.fixTime) { return; } // an older fix arriving late
    state.latest[p.deviceId] = p;
    var ll = [p.latitude, p.longitude];
    var acc = p.accuracy > 0 ? p.accuracy : 0;
    var mk = latestLayer.markers || (latestLayer.markers = {});
    var name = state.devices[p.deviceId] ? state.devices[p.deviceId].name : 'device ' + p.deviceId;
    if (!mk[p.deviceId]) {
      var c = color(p.deviceId);
      mk[p.deviceId] = {
        circle: L.circle(ll, { radius: acc, color: c, weight: 1, fillOpacity: 0.15, interactive: false, pane: 'latest' }),
        dot: L.circleMarker(ll, { radius: 7, color: '#fff', weight: 2, fillColor: c, fillOpacity: 1, pane: 'latest' })
          .bindTooltip(text(name), { permanent: true, direction: 'right', offset: [8, 0] })
      };
      mk[p.deviceId].circle.addTo(latestLayer);
      mk[p.deviceId].dot.addTo(latestLayer);
    } else {
      mk[p.deviceId].circle.setLatLng(ll).setRadius(acc);
      mk[p.deviceId].dot.setLatLng(ll);
    }
    mk[p.deviceId].dot.setTooltipContent(text(name + ' ±' + acc.toFixed(1) + ' m'));
  }

  function onPositions(list, live) {
    var fresh = false, first = Object.keys(state.latest).length === 0;
    list.forEach(function (p) {
      if (!state.devices[p.deviceId]) {
        state.devices[p.deviceId] = { id: p.deviceId, name: 'device ' + p.deviceId };
        fresh = true;
      }
      placeLatest(p);
      if (live) { extendTrack(p); }
    });
    if (fresh) { loadDevices(); }
    if (live && first && list.length && !fenceLayer.getLayers().length) { // an empty map: go to the first
      state.moving = true;
      map.setView([list[0].latitude, list[0].longitude], 16);
    }
    renderDevices();
  }

  function loadDevices() {
    return api('api/devices').then(function (list) {
      list.forEach(function (d) { state.devices[d.id] = d; });
      Object.keys(latestLayer.markers || {}).forEach(function (id) {
        var p = state.latest[id];
        if (p) { latestLayer.markers[id].dot.setTooltipContent(text(state.devices[id].name + ' ±' + p.accuracy.toFixed(1) + ' m')); }
      });
      renderDevices();
    });
  }

  // --- live socket ---------------------------------------------------------------------------
  function connect() {
    var url = location.origin.replace(/^http/, 'ws') + location.pathname.replace(/[^/]*$/, '') +
      'api/socket?token=' + encodeURIComponent(token);
    var ws = new WebSocket(url);
    ws.onopen = function () {
      state.socketOpen = true;
      $('status').textContent = 'live';
      $('status').className = 'status live';
      // positions stored while the socket was (re)connecting are not pushed: read them once
      api('api/positions').then(function (list) { onPositions(list, false); })
        .catch(function (e) { showError(String(e.message || e)); });
    };
    ws.onmessage = function (ev) {
      var msg = JSON.parse(ev.data);
      if (msg.positions) { onPositions(msg.positions, true); }
      if (msg.events) { onLiveEvents(msg.events); }
    };
    ws.onclose = function () {
      state.socketOpen = false;
      $('status').textContent = 'reconnecting';
      $('status').className = 'status';
      setTimeout(connect, 2000);
    };
  }

  // --- a device's track: clean (the service's engine) beside raw (the fixes as sent) ---------
  function toInput(d) { return d.toISOString().slice(0, 19); }

  function uncertainty(p, c, pane, dash) {
    return L.circle([p.latitude, p.longitude], {
      radius: p.accuracy > 0 ? p.accuracy : 0, color: c, weight: 1, fillOpacity: 0.05, dashArray: dash,
      interactive: false, pane: pane
    });
  }

  function rawFix(p) {
    uncertainty(p, RAW, 'raw', '4 4').addTo(rawLayer);
    L.circleMarker([p.latitude, p.longitude], { radius: 4, color: RAW, weight: 1, fillOpacity: 0.9, pane: 'raw' })
      .bindTooltip(text('raw ' + fmtTime(p.fixTime) + ' ±' + p.accuracy.toFixed(1) + ' m')).addTo(rawLayer);
  }

  function showTrack(deviceId, from, to) {
    var t1 = to ? new Date(to) : new Date();
    var t0 = from ? new Date(from) : new Date(t1.getTime() - 3600e3);
    $('track-from').value = toInput(t0);
    $('track-to').value = to ? toInput(t1) : '';
    var period = 'deviceId=' + deviceId + '&from=' + t0.toISOString() + '&to=' +
      (to ? t1.toISOString() : new Date(Date.now() + 86400e3).toISOString());
    var q = 'api/positions?' + period;
    state.report = null;
    var shown = Promise.all([api(q), api(q + '&engine=none')]).then(function (res) {
      var clean = res[0], raw = res[1];
      cleanLayer.clearLayers();
      rawLayer.clearLayers();
      raw.forEach(rawFix);
      var line = L.polyline(clean.map(function (p) { return [p.latitude, p.longitude]; }),
        { color: CLEAN, weight: 3, pane: 'clean' }).addTo(cleanLayer);
      clean.forEach(function (p) { uncertainty(p, CLEAN, 'clean').addTo(cleanLayer); });
      state.track = {
        deviceId: deviceId, from: t0.toISOString(), to: to ? t1.toISOString() : null, live: !to,
        line: line, clean: clean.length, raw: raw.length, engine: state.engine, period: period,
        times: clean.map(function (p) { return Date.parse(p.fixTime); }),
        points: clean.map(function (p) { return [p.latitude, p.longitude]; })
      };
      $('track-info').textContent = clean.length + ' clean positions (' + state.engine + '), ' +
        raw.length + ' raw fixes' + (to ? '' : '; following live');
      var bounds = cleanLayer.getBounds().extend(rawLayer.getBounds());
      if (bounds.isValid()) { fit(bounds, 18); }
      renderDevices();
    });
    // the reports of the same period, drawn once the track (their time reference) is there
    return Promise.all([shown, loadReport(period)]).then(function (res) { showReport(res[1]); })
      .catch(function (e) { showError(String(e.message || e)); });
  }

  function extendTrack(p) {
    var t = state.track;
    if (!t || !t.live || t.deviceId !== p.deviceId || p.fixTime < t.from) { return; }
    t.line.addLatLng([p.latitude, p.longitude]);
    uncertainty(p, CLEAN, 'clean').addTo(cleanLayer);
    t.clean += 1;
    if (state.engine === 'none') { // the socket's rows are the raw fixes themselves
      rawFix(p);
      t.raw += 1;
    }
    $('track-info').textContent = t.clean + ' clean positions (' + state.engine + '), ' + t.raw +
      ' raw fixes; following live';
    t.times.push(Date.parse(p.fixTime));
    t.points.push([p.latitude, p.longitude]);
    // trips and stops change as the device moves: read them again, at most every 10 s
    if (!t.reportDue) {
      t.reportDue = setTimeout(function () {
        if (state.track !== t) { return; }
        t.reportDue = null;
        loadReport(t.period).then(function (r) { if (state.track === t) { showReport(r); } })
          .catch(function (e) { showError(String(e.message || e)); });
      }, 10000);
    }
  }

  // --- trips, stops and events of the track's period -----------------------------------------
  function loadReport(period) {
    return Promise.all(['trips', 'stops', 'events'].map(function (k) { return api('api/reports/' + k + '?' + period); }))
      .then(function (res) { return { trips: res[0], stops: res[1], events: res[2] }; });
  }

  function pad2(n) { return (n < 10 ? '0' : '') + n; }
  function clock(iso) { return iso ? iso.slice(11, 19) : '-'; }
  function fmtDuration(ms) {
    var s = Math.round(ms / 1000), h = Math.floor(s / 3600), mi = Math.floor(s % 3600 / 60);
    if (h) { return h + ' h ' + pad2(mi) + ' min'; }
    return mi ? mi + ' min ' + pad2(s % 60) + ' s' : (s % 60) + ' s';
  }
  function fmtDistance(m) { return m >= 1000 ? (m / 1000).toFixed(2) + ' km' : Math.round(m) + ' m'; }
  var KMH_PER_KNOT = 1.852;

  function segmentText(seg) {
    var head = (seg.kind === 'trip' ? 'Trip ' : 'Stop ') + fmtTime(seg.startTime) + ' → ' + clock(seg.endTime);
    var tail = fmtDuration(seg.duration);
    if (seg.kind === 'trip') {
      tail += ' · ' + fmtDistance(seg.distance) + ' · avg ' + (seg.averageSpeed * KMH_PER_KNOT).toFixed(0) +
        ' km/h · max ' + (seg.maxSpeed * KMH_PER_KNOT).toFixed(0) + ' km/h';
    }
    return [head, tail];
  }

  // an event's words: the type (alert_ prefix off, underscores as spaces) and its zone or reason
  function eventText(e) {
    var a = e.attributes || {}, kind = String(a.kind || e.type).replace(/^alert_/, '');
    var words = { geofence_enter: 'entered', geofence_exit: 'left' };
    if (words[kind] && a.zone !== undefined) { return words[kind] + ' ' + a.zone; }
    var detail = a.zone !== undefined ? a.zone : a.reason;
    return kind.replace(/_/g, ' ') + (detail !== undefined ? ' (' + detail + ')' : '');
  }

  // where an event happened: its own coordinates (alerts carry them), else the clean position
  // nearest to it in time
  function eventPlace(e) {
    var a = e.attributes || {};
    if (typeof a.latitude === 'number' && typeof a.longitude === 'number') { return [a.latitude, a.longitude]; }
    var t = state.track, tt = Date.parse(e.eventTime);
    if (!t || !t.times.length) { return null; }
    var lo = 0, hi = t.times.length - 1;
    while (hi - lo > 1) { var mid = (lo + hi) >> 1; if (t.times[mid] <= tt) { lo = mid; } else { hi = mid; } }
    return t.points[Math.abs(t.times[hi] - tt) < Math.abs(t.times[lo] - tt) ? hi : lo];
  }

  function stopIcon() {
    var el = document.createElement('span');
    el.textContent = 'P';
    return L.divIcon({ className: 'stop-icon', html: el, iconSize: [18, 18] });
  }

  function showReport(r) {
    state.report = r;
    state.selectedEvent = null;
    if (eventMark) { eventMark.remove(); eventMark = null; }
    segLayer.clearLayers();
    var segs = r.trips.map(function (x) { return Object.assign({ kind: 'trip' }, x); })
      .concat(r.stops.map(function (x) { return Object.assign({ kind: 'stop' }, x); }))
      .sort(function (a, b) { return a.startTime < b.startTime ? -1 : a.startTime > b.startTime ? 1 : 0; });
    var ul = $('segments');
    ul.textContent = '';
    segs.forEach(function (seg) {
      var words = segmentText(seg), target;
      if (seg.kind === 'trip') {
        var a = [seg.startLat, seg.startLon], b = [seg.endLat, seg.endLon];
        L.circleMarker(a, { radius: 6, color: '#fff', weight: 2, fillColor: '#2ca02c', fillOpacity: 1, pane: 'marks' })
          .bindTooltip(text('trip start ' + fmtTime(seg.startTime))).addTo(segLayer);
        L.circleMarker(b, { radius: 6, color: '#fff', weight: 2, fillColor: '#b22222', fillOpacity: 1, pane: 'marks' })
          .bindTooltip(text('trip end ' + fmtTime(seg.endTime))).addTo(segLayer);
        target = function () { focusTrip(seg); };
      } else {
        L.marker([seg.latitude, seg.longitude], { icon: stopIcon(), pane: 'marks', keyboard: false })
          .bindTooltip(text('stop ' + fmtDuration(seg.duration) + ' from ' + fmtTime(seg.startTime))).addTo(segLayer);
        target = function () { focusOn([seg.latitude, seg.longitude]); };
      }
      var li = document.createElement('li');
      li.className = seg.kind;
      var head = document.createElement('div'), tail = document.createElement('div');
      head.textContent = words[0];
      tail.className = 'meta';
      tail.textContent = words[1];
      li.appendChild(head);
      li.appendChild(tail);
      li.addEventListener('click', target);
      ul.appendChild(li);
    });
    $('segments-info').textContent = r.trips.length + ' trips, ' + r.stops.length + ' stops, ' +
      r.events.length + ' events';
    renderTimeline();
  }

  function focusOn(ll, zoom) {
    state.moving = true;
    map.setView(ll, Math.max(map.getZoom(), zoom || 17));
  }

  function focusTrip(seg) {
    var t = state.track, t0 = Date.parse(seg.startTime), t1 = Date.parse(seg.endTime);
    var pts = t ? t.points.filter(function (_, i) { return t.times[i] >= t0 && t.times[i] <= t1; }) : [];
    var b = L.latLngBounds(pts.concat([[seg.startLat, seg.startLon], [seg.endLat, seg.endLon]]));
    fit(b, 18);
  }

  function onLiveEvents(list) {
    var t = state.track, r = state.report;
    if (!t || !t.live || !r) { return; }
    var known = {};
    r.events.forEach(function (e) { known[e.id] = true; }); // (a report read meanwhile may have it)
    var fresh = list.filter(function (e) { return e.deviceId === t.deviceId && e.eventTime >= t.from && !known[e.id]; });
    if (!fresh.length) { return; }
    // the socket sends the alert itself; the report's form keeps it under attributes
    fresh.forEach(function (e) {
      r.events.push({ id: e.id, type: e.type, eventTime: e.eventTime, deviceId: e.deviceId,
        attributes: Object.assign({ kind: e.kind, latitude: e.latitude, longitude: e.longitude }, e.attributes || {}) });
    });
    renderTimeline();
  }

  // The timeline under the map: the period's trips and stops as bars, its events as buttons
  // (labels stacked in up to three rows so they do not cover each other), times UTC.
  function renderTimeline() {
    var box = $('timeline'), t = state.track, r = state.report;
    box.textContent = '';
    eventLayer.clearLayers();
    if (!t || !r) { return; }
    var t0 = Date.parse(t.from), t1 = t.to ? Date.parse(t.to) : t0 + 60e3;
    if (!t.to) { // live: up to the latest thing known
      t.times.concat(r.events.map(function (e) { return Date.parse(e.eventTime); }))
        .forEach(function (x) { if (x > t1) { t1 = x; } });
    }
    var span = Math.max(t1 - t0, 1);
    var x = function (iso) { return Math.min(Math.max((Date.parse(iso) - t0) / span, 0), 1) * 100; };
    var width = Math.max(box.clientWidth - 32, 100); // inside the 16 px paddings
    var axis = document.createElement('div');
    axis.className = 'tl-axis';
    var tick = timeStep(span / Math.max(width / 120, 1)); // about 120 px apart, ms
    for (var k = Math.ceil(t0 / tick) * tick; k <= t1; k += tick) {
      var lab = document.createElement('span');
      lab.className = 'tl-tick';
      lab.style.left = ((k - t0) / span * 100) + '%';
      lab.textContent = clock(new Date(k).toISOString()).slice(0, tick % 60e3 ? 8 : 5);
      axis.appendChild(lab);
    }
    box.appendChild(axis);
    var bars = document.createElement('div');
    bars.className = 'tl-bars';
    [['trip', r.trips], ['stop', r.stops]].forEach(function (kv) {
      kv[1].forEach(function (seg) {
        var bar = document.createElement('div');
        bar.className = 'tl-seg ' + kv[0];
        bar.style.left = x(seg.startTime) + '%';
        bar.style.width = Math.max(x(seg.endTime) - x(seg.startTime), 0.2) + '%';
        bar.title = kv[0] + ' ' + fmtTime(seg.startTime) + ' → ' + clock(seg.endTime) + ', ' + fmtDuration(seg.duration);
        bars.appendChild(bar);
      });
    });
    box.appendChild(bars);
    var row = document.createElement('div');
    row.className = 'tl-events';
    var ends = [-1e9, -1e9, -1e9]; // right end (px) of the last label in each row
    r.events.slice().sort(function (a, b) { return a.eventTime < b.eventTime ? -1 : 1; }).forEach(function (e) {
      var words = eventText(e), px = x(e.eventTime) / 100 * width, len = 8 + 7 * (words.length + 9);
      var right = px + len > width; // a label that would run off the end reads leftwards
      var lane = ends.findIndex(function (end) { return end < (right ? px - len : px); });
      if (lane < 0) { lane = ends.indexOf(Math.min.apply(null, ends)); }
      ends[lane] = right ? px : px + len;
      var b = document.createElement('button');
      b.type = 'button';
      b.className = 'tl-event' + (right ? ' right' : '');
      b.dataset.eventId = String(e.id);
      b.style.left = x(e.eventTime) + '%';
      b.style.top = (lane * 20) + 'px';
      b.textContent = clock(e.eventTime) + ' ' + words;
      b.title = e.type + ' ' + fmtTime(e.eventTime);
      b.addEventListener('click', function () { selectEvent(e, b); });
      row.appendChild(b);
      var ll = eventPlace(e);
      if (ll) {
        L.circleMarker(ll, { radius: 5, color: '#fff', weight: 1, fillColor: EVENT, fillOpacity: 1, pane: 'marks' })
          .bindTooltip(text(fmtTime(e.eventTime) + ' ' + words)).on('click', function () { selectEvent(e, b); })
          .addTo(eventLayer);
      }
    });
    box.appendChild(row);
  }

  // the first round time step (s, min, h, days) at least ``ms`` long
  function timeStep(ms) {
    var steps = [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 7200, 10800, 21600, 43200, 86400];
    for (var i = 0; i < steps.length; i++) { if (steps[i] * 1000 >= ms) { return steps[i] * 1000; } }
    return Math.ceil(ms / 86400e3) * 86400e3;
  }

  var eventMark = null;
  function selectEvent(e, b) {
    Array.prototype.forEach.call(document.querySelectorAll('.tl-event.selected'), function (el) { el.classList.remove('selected'); });
    b.classList.add('selected');
    var ll = eventPlace(e);
    state.selectedEvent = { id: e.id, type: e.type, place: ll };
    if (eventMark) { eventMark.remove(); eventMark = null; }
    if (!ll) { showError('event ' + e.id + ' (' + e.type + '): no position to show'); return; }
    eventMark = L.circleMarker(ll, { radius: 12, color: EVENT, weight: 3, fill: false, pane: 'marks', interactive: false })
      .bindTooltip(text(fmtTime(e.eventTime) + ' ' + eventText(e)), { permanent: true, direction: 'left', offset: [-12, 0] })
      .addTo(map);
    focusOn(ll);
  }

  $('track-form').addEventListener('submit', function (ev) {
    ev.preventDefault();
    var id = Number($('track-device').value);
    if (!id) { return; }
    var f = $('track-from').value, t = $('track-to').value;
    showTrack(id, f ? f + 'Z' : null, t ? t + 'Z' : null);
  });

  // --- geofences (Traccar's area text: latitude first) ---------------------------------------
  function parseArea(text) {
    var mm = /^\s*(CIRCLE|POLYGON|LINESTRING)\s*\((.*)\)\s*$/i.exec(text);
    if (!mm) { return null; }
    var kind = mm[1].toUpperCase(), body = mm[2].replace(/[()]/g, '');
    var pts = body.split(',').map(function (s) { return s.trim().split(/\s+/).map(Number); });
    if (kind === 'CIRCLE') { return { kind: kind, centre: pts[0], radius: Number(body.split(',')[1]) }; }
    return { kind: kind, points: pts };
  }

  // a polygon's corners without the ring's closing repeat of the first
  function corners(a) {
    var p = a.points.slice(), f = p[0], l = p[p.length - 1];
    if (p.length > 3 && f[0] === l[0] && f[1] === l[1]) { p.pop(); }
    return p;
  }

  function drawFence(g) {
    var a = parseArea(g.area);
    if (!a) { showError('geofence ' + g.name + ': area not understood: ' + g.area); return; }
    if (state.polygon && state.polygon.original && state.polygon.original.id === g.id) { return; } // being edited
    var style = { color: FENCE, weight: 2, fillOpacity: 0.08, pane: 'fences' };
    var label = { permanent: true, direction: 'top', className: 'fence-label' };
    if (a.kind === 'CIRCLE') { // the name on the circle's northern edge, clear of what is inside
      L.circle(a.centre, Object.assign({ radius: a.radius }, style)).addTo(fenceLayer);
      var north = [a.centre[0] + a.radius / M_PER_DEG, a.centre[1]];
      L.tooltip(label).setLatLng(north).setContent(text(g.name)).addTo(fenceLayer);
    } else if (a.kind === 'POLYGON') { // the name on its northernmost corner, likewise
      L.polygon(a.points, style).addTo(fenceLayer);
      var top = a.points.reduce(function (p, q) { return q[0] > p[0] ? q : p; });
      L.tooltip(label).setLatLng(top).setContent(text(g.name)).addTo(fenceLayer);
    } else {
      L.polyline(a.points, style).bindTooltip(text(g.name), label).addTo(fenceLayer);
    }
  }

  function button(text, onClick) {
    var b = document.createElement('button');
    b.type = 'button';
    b.textContent = text;
    b.addEventListener('click', onClick);
    return b;
  }

  function renderFences() {
    fenceLayer.clearLayers();
    var ul = $('geofences');
    ul.textContent = '';
    state.geofences.forEach(function (g) {
      drawFence(g);
      var li = document.createElement('li');
      li.dataset.geofenceId = g.id;
      var name = document.createElement('span');
      name.textContent = g.name;
      li.appendChild(name);
      var a = parseArea(g.area);
      if (a && a.kind === 'CIRCLE') { li.appendChild(button('edit', function () { startEdit(g, a); })); }
      if (a && a.kind === 'POLYGON') { li.appendChild(button('edit', function () { startPolygon(g, corners(a)); })); }
      li.appendChild(button('delete', function () {
        api('api/geofences/' + g.id, { method: 'DELETE' }).then(loadFences)
          .catch(function (e) { showError(String(e.message || e)); });
      }));
      ul.appendChild(li);
    });
  }

  function loadFences() {
    return api('api/geofences').then(function (list) { state.geofences = list; renderFences(); });
  }

  // a new circle, or an existing one renamed, resized and moved: name and radius in the form,
  // then a click on the map at the centre (POST, or PUT keeping its description and attributes)
  var editing = null, placing = null;
  var HINT = 'Circle: click the map where its centre goes. Polygon: click its corners.';

  function startEdit(g, a) {
    editing = g;
    $('gf-name').value = g.name;
    $('gf-radius').value = String(a.radius);
    $('gf-place').textContent = 'Move / resize "' + g.name + '"';
  }

  function endPlacing() {
    placing = null;
    editing = null;
    map.getContainer().classList.remove('placing');
    $('gf-hint').textContent = HINT;
    $('gf-place').textContent = 'Place circle on map';
  }

  $('geofence-form').addEventListener('submit', function (ev) {
    ev.preventDefault();
    endPolygon();
    placing = { name: $('gf-name').value, radius: Number($('gf-radius').value), original: editing };
    map.getContainer().classList.add('placing');
    $('gf-hint').textContent = 'Click the map where the centre of "' + placing.name + '" goes.';
  });
  map.on('click', function (ev) {
    if (state.polygon) { addCorner(ev.latlng); return; }
    if (!placing) { return; }
    var g = placing, o = g.original;
    endPlacing();
    saveFence(g.name, 'CIRCLE (' + latLonText(ev.latlng) + ', ' + g.radius + ')', o);
  });

  function latLonText(ll) {
    return ll.lat.toFixed(7) + ' ' + L.Util.wrapNum(ll.lng, [-180, 180], true).toFixed(7);
  }

  // POST a new geofence, or PUT ``original`` changed (its description and attributes kept)
  function saveFence(name, area, original) {
    var o = original;
    var body = o ? { name: name, description: o.description, area: area, attributes: o.attributes }
      : { name: name, area: area };
    return api(o ? 'api/geofences/' + o.id : 'api/geofences', {
      method: o ? 'PUT' : 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body)
    }).then(loadFences).catch(function (e) { showError(String(e.message || e)); });
  }

  // --- polygons: a new one corner by corner (each click on the map adds the next), an existing
  // one edited (a click adds a corner on the nearest side); corners are dragged to move them and
  // right-clicked to remove them; "Save polygon" stores the ring (Traccar's POLYGON text, closed)
  var POLY_HINT = 'Click the map at each corner; drag a corner to move it, right-click it to remove it.';
  var polyLayer = L.featureGroup().addTo(map);

  function startPolygon(original, pts) {
    endPlacing();
    endPolygon();
    if (original) { $('gf-name').value = original.name; }
    if (!$('gf-name').value.trim()) { $('gf-name').reportValidity(); return; }
    state.polygon = { original: original, points: pts.map(function (p) { return L.latLng(p[0], p[1]); }) };
    map.getContainer().classList.add('placing');
    $('gf-poly-actions').hidden = false;
    $('gf-draw').hidden = true;
    $('gf-hint').textContent = (original ? 'Editing "' + original.name + '". ' : '') + POLY_HINT;
    if (original) { renderFences(); } // its own outline gives way to the editable one
    drawPolygon();
  }

  function endPolygon() {
    var had = state.polygon;
    state.polygon = null;
    polyLayer.clearLayers();
    $('gf-poly-actions').hidden = true;
    $('gf-draw').hidden = false;
    map.getContainer().classList.remove('placing');
    $('gf-hint').textContent = HINT;
    if (had && had.original) { renderFences(); }
  }

  function drawPolygon() {
    var poly = state.polygon;
    polyLayer.clearLayers();
    var style = { color: FENCE, weight: 2, dashArray: '6 4', fillOpacity: 0.12, pane: 'marks', interactive: false };
    poly.shape = (poly.points.length > 2 ? L.polygon(poly.points, style) : L.polyline(poly.points, style)).addTo(polyLayer);
    poly.points.forEach(function (ll, i) {
      var corner = L.marker(ll, {
        draggable: true, keyboard: false, pane: 'marks',
        icon: L.divIcon({ className: 'corner', iconSize: [12, 12] })
      }).addTo(polyLayer);
      corner.on('drag', function () { poly.points[i] = corner.getLatLng(); poly.shape.setLatLngs(poly.points); });
      corner.on('dragend', function () { poly.points[i] = corner.getLatLng(); drawPolygon(); });
      corner.on('contextmenu', function (ev) {
        L.DomEvent.preventDefault(ev.originalEvent);
        if (poly.points.length > 3) { poly.points.splice(i, 1); drawPolygon(); }
      });
    });
  }

  // a new polygon grows at its end; an edited one gets the corner on the side nearest the click
  function addCorner(ll) {
    var poly = state.polygon, pts = poly.points, at = pts.length;
    if (poly.original && pts.length > 2) {
      var c = map.latLngToContainerPoint(ll), best = Infinity;
      for (var i = 0; i < pts.length; i++) {
        var d = L.LineUtil.pointToSegmentDistance(c, map.latLngToContainerPoint(pts[i]),
          map.latLngToContainerPoint(pts[(i + 1) % pts.length]));
        if (d < best) { best = d; at = i + 1; }
      }
    }
    pts.splice(at, 0, ll);
    drawPolygon();
  }

  $('gf-draw').addEventListener('click', function () { startPolygon(null, []); });
  $('gf-cancel').addEventListener('click', endPolygon);
  $('gf-save').addEventListener('click', function () {
    var poly = state.polygon, name = $('gf-name').value.trim();
    if (!name) { $('gf-name').reportValidity(); return; }
    if (poly.points.length < 3) { $('gf-hint').textContent = 'A polygon needs at least 3 corners. ' + POLY_HINT; return; }
    var ring = poly.points.concat([poly.points[0]]).map(latLonText).join(', ');
    var original = poly.original;
    endPolygon();
    saveFence(name, 'POLYGON ((' + ring + '))', original);
  });

  // --- start ---------------------------------------------------------------------------------
  function start() {
    $('login').hidden = true;
    api('api/server').then(function (s) {
      state.engine = s.engine;
      return Promise.all([loadDevices(), loadFences(), api('api/positions')]);
    }).then(function (res) {
      onPositions(res[2], false);
      var b = latestLayer.getBounds().extend(fenceLayer.getBounds());
      if (b.isValid()) { fit(b, 16); }
      connect();
      state.ready = true;
    }).catch(function (e) { showError(String(e.message || e)); });
  }

  $('login').addEventListener('submit', function (ev) {
    ev.preventDefault();
    token = $('token').value.trim();
    sessionStorage.setItem('iotnav-token', token);
    start();
  });
  if (token) { start(); } else { $('login').hidden = false; $('status').textContent = 'no token'; }

  // map coordinates to the map's pixel (for a console, and the browser test's clicks)
  state.toPixel = function (lat, lon) {
    var pt = map.latLngToContainerPoint([lat, lon]), r = map.getContainer().getBoundingClientRect();
    return { x: pt.x + r.left, y: pt.y + r.top };
  };
  state.map = map;
}());
