// Search from a site opened from disk (file://). Material's search runs in a Web Worker, and
// browsers refuse `new Worker(url)` on a page whose origin is a file. Material's offline plugin
// then loads a shim from a CDN, which a reader without a network never gets; this file is that
// shim, shipped with the site (mkdocs.yml, extra.polyfills: a name with "iframe-worker" in it
// keeps the plugin from adding the CDN's).
//
// The worker's script runs in a hidden iframe whose document is srcdoc, so it has the page's own
// origin and the page may reach into it: `postMessage` to the worker becomes a "message" event
// in the iframe, the iframe's `postMessage` becomes a "message" event on the Worker object. That
// is all Material's search worker uses for an English index (other languages also load lunr's
// stemmers with importScripts, which this shim does not provide). Served over http(s) the
// browser's own Worker is used: nothing here runs.
(function () {
  "use strict";
  if (location.protocol !== "file:") return;

  class FrameWorker extends EventTarget {
    constructor(url) {
      super();
      this.onmessage = null;
      this._inbox = []; // messages posted before the worker's script has run
      this._frame = document.createElement("iframe");
      this._frame.style.display = "none";
      this._frame.addEventListener("load", () => this._start(new URL(url, location.href).href), { once: true });
      this._frame.srcdoc = "<!doctype html><title>worker</title>";
      (document.body || document.documentElement).appendChild(this._frame);
    }

    _start(src) {
      const scope = this._frame.contentWindow;
      // the worker's replies: asynchronous, as a worker's are
      scope.postMessage = (data) => setTimeout(() => this._deliver(data));
      const script = scope.document.createElement("script");
      script.addEventListener("load", () => {
        this._scope = scope;
        this._inbox.splice(0).forEach((data) => this._send(data));
      });
      script.addEventListener("error", () => this.dispatchEvent(new Event("error")));
      script.src = src;
      scope.document.head.appendChild(script);
    }

    _deliver(data) {
      const event = new MessageEvent("message", { data });
      if (typeof this.onmessage === "function") this.onmessage(event);
      this.dispatchEvent(event);
    }

    _send(data) {
      const scope = this._scope;
      setTimeout(() => scope.dispatchEvent(new scope.MessageEvent("message", { data })));
    }

    postMessage(data) {
      if (this._scope) this._send(data);
      else this._inbox.push(data);
    }

    terminate() {
      this._frame.remove();
      this._scope = null;
    }
  }

  window.Worker = FrameWorker;
})();
