// iotnav live map: the fleet's latest clean positions (live over /api/socket), a device's clean
// track beside its raw fixes for a period, geofences (drawn; circles added and deleted), each
// position's uncertainty as a circle of its accuracy radius (metres, as the API gives it).
// Everything comes from the API with the bearer token; nothing is fetched from elsewhere except
// map tiles when the service was given a tile URL.
(function () {
  'use strict';

  var cfg = JSON.parse(document.getElementById('iotnav-config').textContent);
  var COLORS = ['#1f77b4', '#d62728', '#2ca02c', '#9467bd', '#8c564b', '#e377c2', '#17becf', '#bcbd22'];
  var CLEAN = '#1f5fbf', RAW = '#e8771a', FENCE = '#2a9d3a';

  // What the page shows, readable from a console (and by the browser test).
  var state = {
    ready: false, socketOpen: false, engine: null, admin: null,
    devices: {}, latest: {}, track: null, geofences: [], errors: []
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
    var degLat = step / (Math.PI / 180 * 6371008.8);
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
  ['fences', 'clean', 'raw', 'latest'].forEach(function (name, i) {
    map.createPane(name).style.zIndex = String(390 + 10 * i);
  });
  var fenceLayer = L.featureGroup().addTo(map);
  var cleanLayer = L.featureGroup().addTo(map);
  var rawLayer = L.featureGroup().addTo(map);
  var latestLayer = L.featureGroup().addTo(map);
  L.control.layers(null, {
    'Latest positions': latestLayer, 'Clean track': cleanLayer, 'Raw fixes': rawLayer, Geofences: fenceLayer
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
    var q = 'api/positions?deviceId=' + deviceId + '&from=' + t0.toISOString() + '&to=' +
      (to ? t1.toISOString() : new Date(Date.now() + 86400e3).toISOString());
    return Promise.all([api(q), api(q + '&engine=none')]).then(function (res) {
      var clean = res[0], raw = res[1];
      cleanLayer.clearLayers();
      rawLayer.clearLayers();
      raw.forEach(rawFix);
      var line = L.polyline(clean.map(function (p) { return [p.latitude, p.longitude]; }),
        { color: CLEAN, weight: 3, pane: 'clean' }).addTo(cleanLayer);
      clean.forEach(function (p) { uncertainty(p, CLEAN, 'clean').addTo(cleanLayer); });
      state.track = {
        deviceId: deviceId, from: t0.toISOString(), live: !to, line: line,
        clean: clean.length, raw: raw.length, engine: state.engine
      };
      $('track-info').textContent = clean.length + ' clean positions (' + state.engine + '), ' +
        raw.length + ' raw fixes' + (to ? '' : '; following live');
      var bounds = cleanLayer.getBounds().extend(rawLayer.getBounds());
      if (bounds.isValid()) { fit(bounds, 18); }
      renderDevices();
    }).catch(function (e) { showError(String(e.message || e)); });
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

  function drawFence(g) {
    var a = parseArea(g.area);
    if (!a) { showError('geofence ' + g.name + ': area not understood: ' + g.area); return; }
    var style = { color: FENCE, weight: 2, fillOpacity: 0.08, pane: 'fences' };
    var label = { permanent: true, direction: 'top', className: 'fence-label' };
    if (a.kind === 'CIRCLE') { // the name on the circle's northern edge, clear of what is inside
      L.circle(a.centre, Object.assign({ radius: a.radius }, style)).addTo(fenceLayer);
      var north = [a.centre[0] + a.radius / (Math.PI / 180 * 6371008.8), a.centre[1]];
      L.tooltip(label).setLatLng(north).setContent(text(g.name)).addTo(fenceLayer);
    } else {
      (a.kind === 'POLYGON' ? L.polygon(a.points, style) : L.polyline(a.points, style))
        .bindTooltip(text(g.name), label).addTo(fenceLayer);
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
  var HINT = 'Click the map where its centre goes.';

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
    placing = { name: $('gf-name').value, radius: Number($('gf-radius').value), original: editing };
    map.getContainer().classList.add('placing');
    $('gf-hint').textContent = 'Click the map where the centre of "' + placing.name + '" goes.';
  });
  map.on('click', function (ev) {
    if (!placing) { return; }
    var g = placing, o = g.original;
    endPlacing();
    var area = 'CIRCLE (' + ev.latlng.lat.toFixed(7) + ' ' + L.Util.wrapNum(ev.latlng.lng, [-180, 180], true).toFixed(7) +
      ', ' + g.radius + ')';
    var body = o ? { name: g.name, description: o.description, area: area, attributes: o.attributes }
      : { name: g.name, area: area };
    api(o ? 'api/geofences/' + o.id : 'api/geofences', {
      method: o ? 'PUT' : 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body)
    }).then(loadFences).catch(function (e) { showError(String(e.message || e)); });
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
