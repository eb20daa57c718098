// ESLint flat config of the viewer: browser ES modules (no build step), Leaflet as the global `L`.
import js from "@eslint/js";
import globals from "globals";

export default [
  { ignores: ["node_modules/"] },
  js.configs.recommended,
  {
    files: ["**/*.js"],
    languageOptions: {
      ecmaVersion: "latest",
      sourceType: "module",
      globals: { ...globals.browser, L: "readonly" },
    },
  },
];
